"""Reference policies: the oracle's plans are legal and optimal where that is checkable."""

import itertools

import numpy as np
import pytest

from udan.envs import make_vec
from udan.envs.rules import ACTION_DELTAS, FREE, WAIT, WATER
from udan.policies import OraclePolicy, RandomPolicy, assign, distance_field


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
