"""arena/hidden_goal: its rules, and its two bounds checked exactly on a tiny arena."""

from __future__ import annotations

import functools
import itertools

import numpy as np
import pytest

from udan import envs
from udan.envs.hidden_goal import (
    HiddenGoalBatch,
    HiddenGoalConfig,
    no_message_bound,
    oracle_score,
    searcher_bound,
    zone_mask,
)
from udan.envs.rules import ACTION_DELTAS, WAIT
from udan.policies import OraclePolicy


def play(env: HiddenGoalBatch, policy) -> np.ndarray:
    """Team scores (mean agent return) of one episode per arena."""
    done = np.zeros(env.batch, dtype=bool)
    while not done.all():
        _, _, done = env.step(policy(env))
    return env.episode_return.sum(1) / env.present.sum(1)


def test_scout_starts_in_the_zone_and_others_anywhere():
    env = envs.make_vec("arena/hidden_goal", batch=3000, seed=0, agents="2-8", obstacles=0)
    env.reset()
    rows = np.arange(env.batch)
    assert env.in_zone()[rows, env.scout].all()
    counts = env.present.sum(1)
    assert counts.min() == 2 and counts.max() == 8
    assert (env.scout < counts).all()
    # searchers are uniform on the arena: every cell is used, none much more than the mean
    searchers = env.present.copy()
    searchers[rows, env.scout] = False
    cells = env.pos[searchers]
    visits = np.bincount(cells[:, 0] * 9 + cells[:, 1], minlength=81)
    assert visits.min() > 0.6 * visits.mean() and visits.max() < 1.4 * visits.mean()


def test_an_agent_sees_the_goal_only_in_its_zone_and_nothing_of_the_others():
    env = envs.make_vec("arena/hidden_goal", batch=500, seed=1, agents="4", obstacles=0)
    obs = env.reset()
    goal_plane = obs[..., 9:18]
    assert (goal_plane.any(-1) == env.in_zone()).all()
    # the goal's cell in the window is where the goal is
    b, s = np.nonzero(env.in_zone())
    cell = goal_plane[b, s].argmax(-1)
    offset = np.stack([cell // 3 - 1, cell % 3 - 1], axis=-1)
    assert (env.pos[b, s] + offset == env.goal[b]).all()
    assert env.config.spec.size == obs.shape[-1] == 25


def test_others_moves_never_reach_an_agents_observations():
    """Same seed, same actions for agent 0, anything for the others: agent 0 sees the same."""
    first, second = (
        envs.make_vec("arena/hidden_goal", batch=64, seed=7, agents="5", obstacles=0)
        for _ in range(2)
    )
    rng = np.random.default_rng(0)
    seen_a, seen_b = [first.reset()[:, 0]], [second.reset()[:, 0]]
    for _ in range(20):
        act_a, act_b = rng.integers(0, 5, (2, 64, 5))
        act_b[:, 0] = act_a[:, 0]
        seen_a.append(first.step(act_a)[0][:, 0])
        seen_b.append(second.step(act_b)[0][:, 0])
    assert np.array_equal(np.stack(seen_a), np.stack(seen_b))
    assert not np.array_equal(first.pos[:, 1:], second.pos[:, 1:])  # the others did differ


def test_team_reward_is_the_share_in_the_zone_and_walls_alone_stop_moves():
    env = HiddenGoalBatch(HiddenGoalConfig(agents=(3, 3)), batch=1, seed=0)
    env.reset()
    env.goal[0] = (4, 4)
    env.pos[0] = [(4, 5), (4, 5), (0, 0)]  # two agents share a cell: nothing blocks
    _, reward, _ = env.step(np.array([[WAIT, 2, 0]]))  # wait, left (onto the goal), up (wall)
    assert env.pos[0].tolist() == [[4, 5], [4, 4], [0, 0]]
    assert np.allclose(reward, 2 / 3)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"agents": 1}, "at least 2 agents"),
        ({"obstacles": "0-3"}, "no obstacles"),
        ({"churn": 0.1}, "churn must be 0"),
    ],
)
def test_bad_configs_are_refused(options, message):
    with pytest.raises(envs.EnvConfigError, match=message):
        envs.make_vec("arena/hidden_goal", batch=1, **options)


def test_oracle_policy_scores_the_exact_oracle():
    env = envs.make_vec("arena/hidden_goal", batch=20000, seed=3, agents="4", obstacles=0)
    env.reset()
    oracle = OraclePolicy()
    scores = play(env, lambda e: oracle.act(e))
    exact = oracle_score(9, 9, 20, 4)
    assert abs(scores.mean() - exact) < 4 * scores.std() / np.sqrt(scores.size)


# ------------------------------------------------------------------- the bound, solved exactly
HEIGHT, WIDTH, STEPS = 3, 3, 4
CELLS = [(r, c) for r in range(HEIGHT) for c in range(WIDTH)]


def _move(pos: tuple[int, int], action: int) -> tuple[int, int]:
    r, c = pos[0] + ACTION_DELTAS[action][0], pos[1] + ACTION_DELTAS[action][1]
    return (r, c) if 0 <= r < HEIGHT and 0 <= c < WIDTH else pos


def _near(pos: tuple[int, int]) -> frozenset:
    return frozenset(g for g in CELLS if abs(g[0] - pos[0]) + abs(g[1] - pos[1]) <= 1)


@functools.cache
def _known(t: int, pos: tuple[int, int], goal: tuple[int, int]) -> float:
    """Best expected reward from step t on with the goal known (every policy, by Bellman)."""
    if t == STEPS:
        return 0.0
    best = 0.0
    for a in range(5):
        nxt = _move(pos, a)
        best = max(best, float(goal in _near(nxt)) + _known(t + 1, nxt, goal))
    return best


@functools.cache
def _searching(t: int, pos: tuple[int, int], candidates: frozenset) -> tuple[float, int]:
    """(best expected reward from step t on, its action) for a searcher that has not seen the
    goal, which is uniform over ``candidates``: the exact optimum over every closed-loop policy
    on its own observations."""
    if t == STEPS:
        return 0.0, WAIT
    best = (-1.0, WAIT)
    for a in range(5):
        nxt = _move(pos, a)
        seen = candidates & _near(nxt)
        value = sum(1.0 + _known(t + 1, nxt, g) for g in seen) / len(candidates)
        rest = candidates - seen
        if rest:
            value += len(rest) / len(candidates) * _searching(t + 1, nxt, rest)[0]
        best = max(best, (value, a), key=lambda va: va[0])
    return best


def _exact_searcher(start: tuple[int, int]) -> float:
    """Expected score of the best lone searcher from ``start``, the goal uniform on the arena."""
    seen = _near(start)
    value = sum(_known(0, start, g) for g in seen)
    rest = frozenset(CELLS) - seen
    value += len(rest) * _searching(0, start, rest)[0]
    return value / len(CELLS)


def _best_fixed_path(start: tuple[int, int]) -> float:
    """Every open-loop path of the searcher enumerated: the best one's expected score."""
    best = 0.0
    for path in itertools.product(range(5), repeat=STEPS):
        pos, covered, score = start, set(_near(start)), 0.0
        for a in path:
            pos = _move(pos, a)
            covered |= _near(pos)
            score += len(covered) / len(CELLS)
        best = max(best, score)
    return best


def test_searcher_bound_holds_and_is_what_a_fixed_path_reaches():
    bound = searcher_bound(HEIGHT, WIDTH, STEPS)
    for start in CELLS:
        exact = _exact_searcher(start)
        assert exact == pytest.approx(_best_fixed_path(start))  # the lemma: a path is enough
        assert exact <= bound[start] + 1e-9


class _ExactSearchers:
    """Every agent plays the exact optimal lone search on its own observations (the env's)."""

    def __init__(self, env: HiddenGoalBatch) -> None:
        self.candidates = {}
        self.env = env

    def __call__(self, env: HiddenGoalBatch) -> np.ndarray:
        obs, t = env.observe(), int(env.t[0])
        actions = np.full((env.batch, env.slots), WAIT)
        for b, s in zip(*np.nonzero(env.present), strict=True):
            pos = tuple(env.pos[b, s])
            if obs[b, s, 9:18].any():  # seen: stand still in the zone
                continue
            rest = self.candidates.get((b, s), frozenset(CELLS)) - _near(pos)
            self.candidates[b, s] = rest
            actions[b, s] = _searching(t, pos, rest)[1]
        return actions


def test_a_team_without_messages_scores_the_bound_formula_on_the_tiny_arena():
    """The exact lone search played by every agent in the real env: the team's score is the
    formula's (scout T, searchers their exact value), which nothing without messages beats."""
    agents = 3
    config = HiddenGoalConfig(agents=(agents, agents), height=HEIGHT, width=WIDTH, max_steps=STEPS)
    env = HiddenGoalBatch(config, batch=6000, seed=5)
    env.reset()
    scores = play(env, _ExactSearchers(env))
    searcher = np.mean([_exact_searcher(s) for s in CELLS])
    expected = (STEPS + (agents - 1) * searcher) / agents
    assert abs(scores.mean() - expected) < 4 * scores.std() / np.sqrt(scores.size)
    assert expected <= no_message_bound(HEIGHT, WIDTH, STEPS, agents) + 1e-9
    assert oracle_score(HEIGHT, WIDTH, STEPS, agents) >= expected


def test_zone_mask_is_the_goal_and_its_neighbours_on_the_arena():
    corner = zone_mask(np.array([0, 0]), 4, 5)
    assert corner.sum() == 3 and corner[0, 0] and corner[1, 0] and corner[0, 1]
    assert zone_mask(np.array([2, 2]), 4, 5).sum() == 5
