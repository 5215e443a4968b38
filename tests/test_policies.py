"""Reference policies: the oracle's plans are legal and optimal where that is checkable."""

import itertools

import numpy as np
import pytest

from udan.envs import make_vec
from udan.envs.rules import ACTION_DELTAS, FREE, WAIT, WATER
from udan.policies import (
    ChaserPolicy,
    LinerPolicy,
    OraclePolicy,
    RandomPolicy,
    assign,
    distance_field,
)


def play(env, policy):
    env.reset()
    policy.reset(env)
    blocked = 0
    done = np.zeros(env.batch, bool)
    while not done.all():
        act = policy.act(env)
        before, present = env.pos.copy(), env.present.copy()
        _, _, done = env.step(act)
        wanted = before + ACTION_DELTAS[act]
        blocked += int((present & (act != WAIT) & (env.pos != wanted).any(-1)).sum())
    return blocked


def test_find_water_oracle_plans_execute_exactly():
    env = make_vec("arena/find_water", batch=150, seed=11, agents=(1, 5), obstacles=(0, 14))
    assert play(env, OraclePolicy(seed=0)) == 0


def test_find_water_oracle_is_optimal_for_one_agent():
    env = make_vec("arena/find_water", batch=40, seed=5, agents=(1, 1), obstacles=(0, 9))
    env.reset()
    starts = env.pos[:, 0].copy()
    layouts = env.layout.copy()
    play_env = make_vec("arena/find_water", batch=40, seed=5, agents=(1, 1), obstacles=(0, 9))
    play(play_env, OraclePolicy())
    for b in range(40):
        passable = layouts[b] == FREE
        goals = [(1, c) for c in np.flatnonzero(layouts[b, 0] == WATER)]
        d = min(distance_field(passable, g)[tuple(starts[b])] for g in goals)
        expected = 0 if np.isinf(d) else 50 - d + 1  # paid from the step it arrives on
        assert play_env.episode_return[b, 0] == expected


@pytest.mark.parametrize("task", ["find_water", "surround"])
def test_oracle_far_above_random(task):
    scores = {}
    for name, policy in [("oracle", OraclePolicy()), ("random", RandomPolicy())]:
        env = make_vec(f"arena/{task}", batch=60, seed=2, agents=(1, 5), obstacles=(0, 9))
        play(env, policy)
        scores[name] = float(env.episode_return.sum() / env.present.sum())
    assert scores["oracle"] > scores["random"] + 15, scores


def test_surround_oracle_tracks_a_lone_target():
    env = make_vec("arena/surround", batch=30, seed=4, agents=(1, 1), obstacles=(0, 0))
    play(env, OraclePolicy())
    assert env.episode_return[:, 0].mean() > 30


def test_assign_is_minimum_total_cost():
    rng = np.random.default_rng(0)
    for _ in range(20):
        cost = rng.integers(0, 10, size=(4, 4)).astype(float)
        goals = assign(cost)
        assert sorted(goals) == [0, 1, 2, 3]
        best = min(sum(cost[i, p[i]] for i in range(4)) for p in itertools.permutations(range(4)))
        assert sum(cost[i, g] for i, g in enumerate(goals)) == best
    # more agents than goals: the extra agent reuses its nearest goal
    assert assign(np.array([[0.0, 5.0], [5.0, 0.0], [1.0, 9.0]])) == [0, 1, 0]


def test_distance_field_goes_around_walls():
    passable = np.ones((3, 3), bool)
    passable[1, :2] = False
    field = distance_field(passable, (0, 0))
    assert (
        field[2, 0] == 6 and np.isinf(distance_field(passable[:1, :1] & False, (0, 0))).sum() == 0
    )


@pytest.mark.magent
def test_the_chaser_attacks_in_range_closes_in_on_what_it_sees_and_walks_on_otherwise():
    from udan.envs.magent import make, move_offsets

    env = make("magent/pursuit", agents=3, map_size=30, seed=0)
    layout = {"agents": [(5, 5), (20, 20), (10, 25)], "opponents": [(6, 6), (20, 24)], "walls": []}
    env.reset(options={"layout": layout})
    heading = np.array([0, 0, 3])
    got = ChaserPolicy(seed=1).act_in(env, heading)
    moves = move_offsets(env.agent_attrs["speed"]).tolist()
    assert got["agent_0"] == env.attack_action(1, 1)  # 1.4 cells: in range 2
    assert moves[got["agent_1"]] == [0, 1]  # 4 cells down: in view 5, out of range
    assert moves[got["agent_2"]] in ([0, 1], [0, -1], [-1, 0], [1, 0])  # sees none: walks
    assert heading[:2].tolist() == [0, 0]  # the two that saw a sheep kept their heading


@pytest.mark.magent
def test_the_chaser_scores_where_random_wolves_only_pay_for_attacks():
    from udan.evaluate import evaluate

    def score(policy):
        options = {"map_size": 20, "max_steps": 60}
        return evaluate("magent/pursuit", policy, (6, 6), (0, 0), 2, 3, options)[0].scores.mean()

    assert score(ChaserPolicy()) > 5 > 0 > score(RandomPolicy())
    with pytest.raises(ValueError, match="pursuit, tiger"):
        evaluate("magent/queue", ChaserPolicy(), (3, 3), (0, 0), 1, 0, {"map_size": 10})


@pytest.mark.magent
def test_the_liner_steps_west_falls_south_at_the_wall_and_goes_round_a_taken_cell():
    from udan.envs.magent import make, move_offsets

    env = make("magent/queue", agents=5, map_size=12, seed=0)
    bottom = 10  # the row above the south wall
    layout = {"agents": [(6, 4), (1, 3), (1, bottom), (2, bottom), (1, bottom - 1)], "walls": []}
    env.reset(options={"layout": layout})
    got = LinerPolicy().act_in(env)
    moves = move_offsets(env.agent_attrs["speed"]).tolist()
    assert moves[got["agent_0"]] == [-1, 0]  # west is free
    assert moves[got["agent_1"]] == [0, 1]  # at the west wall, falls south
    assert got["agent_2"] == env.stay_action  # bottom of the stack
    assert moves[got["agent_3"]] == [0, -1]  # west taken: north, round the stack
    assert got["agent_4"] == env.stay_action  # on the stack


@pytest.mark.magent
def test_the_liner_lines_up_every_episode_where_random_agents_never_do():
    from udan.evaluate import evaluate

    def scores(policy, agents):
        cells = evaluate("magent/queue", policy, agents, (0, 0), 3, 0)
        return np.concatenate([c.scores for c in cells]), [c.line_walk for c in cells]

    lined, walks = scores(LinerPolicy(), (8, 20))  # the paper's map 30 and 300 steps
    assert (lined > -0.2 * 100).all(), lined  # +1 for the line within 100 steps, every episode
    assert walks == [0.0] * 13  # a fleet in line has nothing left to walk
    lost, walks = scores(RandomPolicy(), (8, 9))
    assert np.allclose(lost, -60.0)  # 300 steps at -0.2, no line
    assert all(walk > 1 for walk in walks), walks  # scattered: cells from any line
    with pytest.raises(ValueError, match="queue"):
        evaluate("magent/pursuit", LinerPolicy(), (3, 3), (0, 0), 1, 0, {"map_size": 10})
    with pytest.raises(ValueError, match="inner walls"):
        evaluate("magent/queue", LinerPolicy(), (3, 3), (2, 2), 1, 0, {"map_size": 10})
