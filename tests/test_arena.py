"""The vectorised arena core: layouts, rewards, churn, registry and bad input."""

import warnings

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import udan.envs as envs
from udan.envs.arena import ArenaBatch, ArenaConfig, scene_codes, task_rewards
from udan.envs.observe import AGENT_BIT, OBJECTIVE_BIT
from udan.envs.rules import FREE, OBSTACLE, WAIT, WATER


def fresh(task, batch=64, seed=0, **kw):
    env = ArenaBatch(ArenaConfig(task=task, **kw), batch=batch, seed=seed)
    env.reset()
    return env


@pytest.mark.parametrize("task", ["find_water", "surround"])
def test_counts_are_drawn_within_the_ranges(task):
    env = fresh(task, batch=400, agents=(2, 4), obstacles=(3, 7))
    n = env.present.sum(1)
    m = (env.layout == OBSTACLE).sum((1, 2))
    assert n.min() == 2 and n.max() == 4
    assert m.min() == 3 and m.max() == 7
    # agents stand on free cells, one per cell
    b, s = np.nonzero(env.present)
    assert (env.layout[b, env.pos[b, s, 0], env.pos[b, s, 1]] == FREE).all()
    for i in range(env.batch):
        cells = {tuple(p) for p in env.pos[i, env.present[i]].tolist()}
        assert len(cells) == n[i]


def test_find_water_layout():
    env = fresh("find_water", batch=200)
    for b in range(env.batch):
        n = env.present[b].sum()
        row0 = env.layout[b, 0]
        src = np.flatnonzero(row0 == WATER)
        assert len(src) == n and (np.diff(src) == 1).all(), "a contiguous row of N sources"
        for end in (src[0] - 1, src[-1] + 1):
            if 0 <= end < 9:
                assert row0[end] != FREE, "sources walled at both ends"
        assert (env.layout[b, 1] == FREE).all(), "the drinking row is open"
        obst_rows = np.nonzero(env.layout[b] == OBSTACLE)[0]
        assert ((obst_rows >= 2) & (obst_rows <= 4)).all()
        assert (env.pos[b, env.present[b], 0] >= 5).all(), "agents start in the start zone"


def test_find_water_pays_one_per_step_in_front_of_a_source():
    env = fresh("find_water", batch=1, agents=(2, 2), obstacles=(0, 0))
    src = np.flatnonzero(env.layout[0, 0] == WATER)
    env.pos[0] = [[1, src[0]], [2, src[1]]]
    _, reward, _ = env.step(np.full((1, 2), WAIT))
    assert reward[0].tolist() == [1.0, 0.0]
    env.pos[0, 0] = [1, 0]  # front row, but no source above (walled or bare)
    _, reward, _ = env.step(np.full((1, 2), WAIT))
    assert reward[0, 0] == 0.0


def test_surround_scores_adjacency_and_penalises_every_fourth_step():
    env = fresh("surround", batch=1, agents=(2, 2), obstacles=(0, 0))
    env.layout[0] = FREE
    env.layout[0, 1, 0] = OBSTACLE  # the target in the corner, pinned by agent 0 and a wall
    env.target[0] = [0, 0]
    env.pos[0] = [[0, 1], [8, 8]]
    rewards = [env.step(np.full((1, 2), WAIT))[1][0].tolist() for _ in range(8)]
    assert env.target[0].tolist() == [0, 0]
    assert [a for a, _ in rewards] == [1.0] * 8
    assert [b for _, b in rewards] == [0, 0, 0, -1, 0, 0, 0, -1]
    assert env.target_score[0] == -8
    assert env.adjacent_steps[0].tolist() == [8, 0]  # the paper's goal score: -4 per agent


def _previous_task_rewards(task, layout, pos, present, target, t):
    """task_rewards as numpy arrays, before its loop moved to udan._kernels (commit b68a9ec):
    the oracle the C loop is held to."""
    if task == "find_water":
        front = pos[..., 0] == 1
        source = layout[np.arange(len(layout))[:, None], 0, pos[..., 1]] == WATER
        reward = (front & source).astype(np.float32)
    else:
        adjacent = np.abs(pos - target[:, None]).sum(-1) == 1
        penalty = (np.asarray(t) % 4 == 0)[:, None] & ~adjacent
        reward = adjacent.astype(np.float32) - penalty.astype(np.float32)
    return np.where(present, reward, 0.0).astype(np.float32)


@pytest.mark.parametrize("task", ["find_water", "surround"])
def test_rewards_are_bit_for_bit_those_of_the_previous_array_code(task):
    rng = np.random.default_rng(3)
    for _ in range(200):
        batch, n, height, width = (int(v) for v in rng.integers(1, 9, 4))
        layout = rng.choice([FREE, OBSTACLE, WATER], (batch, height, width)).astype(np.uint8)
        pos = np.stack(
            [rng.integers(0, height, (batch, n)), rng.integers(0, width, (batch, n))], -1
        )
        target = np.stack([rng.integers(0, height, batch), rng.integers(0, width, batch)], -1)
        present, t = rng.random((batch, n)) < 0.8, rng.integers(0, 50, batch)
        want = _previous_task_rewards(task, layout, pos, present, target, t)
        assert task_rewards(task, layout, pos, present, target, t).tobytes() == want.tobytes()


def _previous_scene_codes(padded_layout, pos, present, view, target=None):
    """scene_codes as numpy arrays, before its loop moved to udan._kernels (commit b68a9ec)."""
    codes = padded_layout.copy()
    batch, hp, wp = codes.shape
    flat = codes.reshape(-1)
    origin = view * wp + view
    arenas = np.arange(batch)[:, None] * (hp * wp) + origin if batch > 1 else origin
    flat[(pos[..., 0] * wp + pos[..., 1] + arenas)[present]] |= AGENT_BIT
    if target is not None:
        flat[target[:, 0] * wp + target[:, 1] + np.ravel(arenas)] |= OBJECTIVE_BIT
    return codes


def test_scene_codes_are_those_of_the_previous_array_code():
    """Agents anywhere on the arena (several on one cell too), absent ones, a target or none,
    and the edge's (-1, -1) for a target not seen: the same bytes."""
    rng = np.random.default_rng(4)
    for _ in range(200):
        batch, n, height, width = (int(v) for v in rng.integers(1, 9, 4))
        view = int(rng.integers(1, 4))
        padded = rng.integers(0, 8, (batch, height + 2 * view, width + 2 * view)).astype(np.uint8)
        rows, cols = rng.integers(0, height, (batch, n)), rng.integers(0, width, (batch, n))
        pos, present = np.stack([rows, cols], -1), rng.random((batch, n)) < 0.7
        target = np.stack([rng.integers(-1, height, batch), rng.integers(-1, width, batch)], -1)
        for seen in (None, target):
            want = _previous_scene_codes(padded, pos, present, view, seen)
            assert scene_codes(padded, pos, present, view, seen).tobytes() == want.tobytes()


def test_surround_target_flees_and_a_follower_stays_adjacent():
    env = fresh("surround", batch=1, agents=(1, 1), obstacles=(0, 0))
    env.target[0] = [4, 4]
    env.pos[0, 0] = [4, 3]
    assert env.flee_scores()[0].argmax() != WAIT
    _, r, _ = env.step(np.array([[3]]))  # right: into the cell the target leaves
    assert env.pos[0, 0].tolist() == [4, 4]
    assert env.target[0].tolist() != [4, 4]
    assert r[0, 0] == 1.0


def test_episode_ends_at_max_steps_and_reset_is_selective():
    env = fresh("find_water", batch=3, max_steps=5)
    for t in range(5):
        _, _, done = env.step(np.full((3, 5), WAIT))
        assert done.all() == (t == 4)
    before = env.pos.copy()
    env.reset(np.array([True, False, False]))
    assert (env.t == [0, 5, 5]).all()
    assert (env.pos[1:] == before[1:]).all()


def test_same_seed_same_episodes():
    a, b = fresh("surround", seed=7), fresh("surround", seed=7)
    rng = np.random.default_rng(0)
    for _ in range(10):
        act = rng.integers(0, 5, (64, 5))
        oa, ra, _ = a.step(act)
        ob, rb, _ = b.step(act)
        assert (oa == ob).all() and (ra == rb).all()


def test_churn_changes_membership_with_fresh_ids():
    env = fresh("surround", batch=50, agents=(1, 5), churn=0.5)
    seen_join = seen_leave = False
    for _ in range(40):
        env.step(np.random.default_rng(0).integers(0, 5, (50, 5)))
        seen_join |= bool(env.joined.any())
        seen_leave |= bool(env.left.any())
        assert (env.present.sum(1) >= 1).all() and (env.present.sum(1) <= 5).all()
        assert not (env.joined & ~env.present).any()
        assert not (env.left & env.present).any()
    assert seen_join and seen_leave
    for b in range(50):
        ids = env.agent_id[b, env.present[b]]
        assert len(set(ids.tolist())) == len(ids)


def test_global_state_and_render():
    env = fresh("find_water", batch=2)
    state = env.global_state()
    assert state.shape == (2, 3 * 81)
    assert state[:, 81:162].sum(1).tolist() == env.present.sum(1).tolist()
    picture = env.render(0)
    assert picture.count("~") == env.present[0].sum() and len(picture.splitlines()) == 9


@pytest.mark.parametrize("name", [n for n in envs.env_names() if n.startswith("arena/")])
@pytest.mark.parametrize("churn", [0.0, 0.3])
def test_parallel_api(name, churn):
    if name == "arena/hidden_goal" and churn:  # N is fixed within its episodes
        with pytest.raises(envs.EnvConfigError, match="churn must be 0"):
            envs.make(name, churn=churn, seed=1)
        return
    env = envs.make(name, churn=churn, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # N differs per episode, so possible_agents always holds names that never appeared
        warnings.filterwarnings("ignore", message="No agents present but not all possible_agents")
        parallel_api_test(env, num_cycles=120)


def test_parallel_env_matches_the_core():
    env = envs.make("arena/find_water", seed=3)
    obs, _ = env.reset(seed=3)
    core = envs.make_vec("arena/find_water", batch=1, seed=3)
    core_obs = core.reset()
    assert [f"agent_{i}" for i in range(core.present[0].sum())] == env.agents
    for i, agent in enumerate(env.agents):
        assert (obs[agent] == core_obs[0, i]).all()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"agents": (0, 3)}, "at least 1 agent"),
        ({"agents": (4, 2)}, "inverted"),
        ({"agents": "a-b"}, "range like 1-5"),
        ({"agents": (1, 10)}, "water sources"),
        ({"obstacles": (0, 28)}, "obstacle zone"),
        ({"task": "surround", "agents": (1, 40), "obstacles": (0, 41)}, "exceed the 81 cells"),
        ({"churn": 2.0}, "probability"),
        ({"agents": 3, "churn": 0.2}, "churn needs a range of agents"),
        ({"task": "fly"}, "unknown arena task"),
    ],
)
def test_bad_config_is_refused_with_a_clear_message(kwargs, message):
    with pytest.raises(envs.EnvConfigError, match=message):
        ArenaConfig(**{"task": "find_water", **kwargs})


def test_unknown_env_names_the_known_ones(monkeypatch):
    with pytest.raises(envs.UnknownEnvError, match=r"known: .*arena/find_water"):
        envs.make("arena/nope")
    assert envs.make_vec("magent/tiger", batch=2, agents=3).batch == 2
    monkeypatch.setitem(envs._PARALLEL, "magent/extra", "udan.envs.magent:make")
    with pytest.raises(envs.UnknownEnvError, match="no vectorised form"):
        envs.make_vec("magent/extra", batch=2)


def test_bad_actions_are_refused():
    env = fresh("find_water", batch=1)
    with pytest.raises(ValueError, match="actions must be in"):
        env.step(np.full((1, 5), 7))


@pytest.mark.parametrize(
    ("actions", "message"),
    [
        (np.full((2, 5), 1.0), "must be integers"),
        (np.full((2, 5), "1"), "must be integers"),
        (np.full((2, 4), 1), "one per slot"),
        (np.full((2, 5), 7), "in 0..4"),
        (np.full((2, 5), -1), "in 0..4"),
    ],
)
def test_loose_actions_are_refused(actions, message):
    env = fresh("find_water", batch=2, agents=(5, 5))
    with pytest.raises(ValueError, match=message):
        env.step(actions)


def test_a_step_after_the_episode_ended_is_refused():
    env = fresh("surround", batch=2, agents=(2, 2))
    for _ in range(env.config.max_steps):
        env.step(np.zeros((2, 2), dtype=np.int64))
    with pytest.raises(ValueError, match="episode over"):
        env.step(np.zeros((2, 2), dtype=np.int64))
    env.reset()
    env.step(np.zeros((2, 2), dtype=np.int64))


def test_parallel_view_wants_an_integer_action_from_every_agent_and_none_after_the_end():
    env = envs.make("arena/find_water", agents=(3, 3), seed=0)
    env.reset()
    everyone = dict.fromkeys(env.agents, 4)
    with pytest.raises(ValueError, match="missing"):
        env.step(dict(list(everyone.items())[:2]))
    with pytest.raises(ValueError, match="not in the episode"):
        env.step({**everyone, "agent_9": 0})
    with pytest.raises(ValueError, match="an action is an integer"):
        env.step({**everyone, env.agents[0]: 1.5})
    for _ in range(env.config.max_steps):
        env.step(dict.fromkeys(env.agents, 4))
    with pytest.raises(ValueError, match="episode is over"):
        env.step(everyone)


def test_joiners_find_the_water_the_episode_started_with():
    env = fresh("find_water", batch=64, agents=(1, 5), churn=0.5)
    env.reset()
    sources = (env.layout[:, 0] == WATER).sum(1)
    counts = env.present.sum(1)
    assert (sources == counts).all()
    for _ in range(env.config.max_steps):
        env.step(np.full((64, 5), 4))
        assert ((env.layout[:, 0] == WATER).sum(1) == sources).all()
    assert (env.present.sum(1) != counts).any()  # the fleets did change
