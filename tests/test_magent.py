"""MAgent scenarios on the real MAgent2 engine: PettingZoo API, counts per episode, reward rules."""

from __future__ import annotations

import hashlib
import warnings

import numpy as np
import pytest

pytest.importorskip("magent2")

from pettingzoo.test import parallel_api_test

import udan.envs
from udan.envs.errors import EnvConfigError, UnknownEnvError
from udan.envs.magent import make, move_offsets

pytestmark = pytest.mark.magent

SCENARIOS = ["magent/pursuit", "magent/tiger", "magent/queue"]
#: parallel_api_test's complaint when an episode ends with fewer agents than possible_agents,
#: which is every episode here: N is drawn per episode below the maximum.
VARYING_N = "No agents present but not all possible_agents are terminated or truncated"


def _api_test(env, num_cycles: int) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.filterwarnings("ignore", message=VARYING_N)
        parallel_api_test(env, num_cycles=num_cycles)


def _step(env, actions: dict[str, int]):
    """One step in which every present agent not named in ``actions`` stays."""
    full = dict.fromkeys(env.agents, env.stay_action)
    full.update(actions)
    return env.step(full)


@pytest.mark.parametrize("name", SCENARIOS)
def test_parallel_api_small_until_episodes_end(name: str) -> None:
    env = make(name, agents=(2, 5), obstacles=(0, 6), map_size=16, max_steps=12, seed=1)
    _api_test(env, num_cycles=20)


@pytest.mark.parametrize("name", SCENARIOS)
def test_parallel_api_default_map_through_registry(name: str) -> None:
    env = udan.envs.make(name, agents="8-20", seed=0)
    assert env.map_size == {"magent/pursuit": 100, "magent/tiger": 50, "magent/queue": 30}[name]
    _api_test(env, num_cycles=25)


@pytest.mark.parametrize("name", SCENARIOS)
def test_agent_count_varies_within_range_and_follows_seed(name: str) -> None:
    def counts(seed: int) -> list[int]:
        env = make(name, agents=(2, 9), map_size=20, seed=seed)
        return [len(env.reset()[0]) for _ in range(15)]

    first = counts(7)
    assert all(2 <= n <= 9 for n in first)
    assert len(set(first)) > 2
    assert counts(7) == first
    assert counts(8) != first


@pytest.mark.parametrize("name", SCENARIOS)
def test_same_seed_same_trajectory(name: str) -> None:
    def run(env) -> list[np.ndarray]:
        obs, _ = env.reset(seed=5)
        rng = np.random.default_rng(0)
        frames = [np.stack([obs[a] for a in env.agents])]
        for _ in range(10):
            acts = {a: int(rng.integers(env.action_space(a).n)) for a in env.agents}
            obs = env.step(acts)[0]
            frames.append(np.stack(list(obs.values())))
            frames.append(env.state())
        return frames

    env = make(name, agents=(3, 6), obstacles=4, map_size=16, seed=0)
    a, b = run(env), run(make(name, agents=(3, 6), obstacles=4, map_size=16, seed=99))
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("name", SCENARIOS)
def test_spaces_state_and_render(name: str) -> None:
    env = make(name, agents=(2, 4), obstacles=3, map_size=12, seed=2, render_mode="ansi")
    obs, _ = env.reset()
    assert env.possible_agents == ["agent_0", "agent_1", "agent_2", "agent_3"]
    assert env.agents == env.possible_agents[: len(env.agents)]
    space = env.observation_space("agent_0")
    assert space is env.observation_space("agent_3")
    assert space.shape == (env.obs_size,)
    assert all(space.contains(o) for o in obs.values())
    state = env.state()
    assert env.state_space.contains(state)
    board = env.render()
    assert board.count("A") == len(env.agents)
    assert board.count("#") == 4 * 11 + 3


def test_engine_moves_match_move_table() -> None:
    env = make("magent/queue", agents=1, map_size=9)
    for action, (dx, dy) in enumerate(move_offsets(1)):
        env.reset(options={"layout": {"agents": [(4, 4)]}})
        env.step({"agent_0": action})
        assert tuple(env.positions()[0][0]) == (4 + dx, 4 + dy)
    assert len(move_offsets(1.5)) == 9  # sheep: stay + 8 neighbours


def test_pursuit_attack_rule() -> None:
    # A sheep cornered at (1, 1) by three wolves cannot move (walls and wolves all round).
    env = make("magent/pursuit", agents=(3, 3), map_size=10)
    env.reset(options={"layout": {"agents": [(2, 1), (1, 2), (2, 2)], "opponents": [(1, 1)]}})
    _, rew, *_ = _step(
        env, {"agent_0": env.attack_action(-1, 0), "agent_1": env.attack_action(0, 2)}
    )
    assert rew == pytest.approx({"agent_0": 0.8, "agent_1": -0.2, "agent_2": 0.0})
    _, rew, *_ = _step(env, {"agent_2": env.attack_action(-1, -1)})
    assert rew == pytest.approx({"agent_0": 0.0, "agent_1": 0.0, "agent_2": 0.8})


def test_sheep_flee_from_a_wolf_in_view() -> None:
    env = make("magent/pursuit", agents=1, map_size=20, seed=3)
    env.reset(options={"layout": {"agents": [(9, 9)], "opponents": [(10, 10)]}})
    _step(env, {})
    sheep = env.positions()[1][0]
    assert tuple(sheep) == (11, 11)  # the one neighbour farthest from the wolf


@pytest.mark.parametrize(("alertness", "fled"), [(1.0, (1.0, 1.0)), (0.5, (0.35, 0.65)),
                                                (0.0, (0.05, 0.2))])  # fmt: skip
def test_prey_alertness_is_the_share_of_steps_a_sheep_in_view_flees(alertness, fled) -> None:
    """A sheep next to a wolf flees to the one farthest cell when alert, wanders when not (1 of
    its 9 moves is that cell): over 400 such steps it reaches (11, 11) on about
    ``alertness + (1 - alertness) / 9`` of them."""
    env = make("magent/pursuit", agents=1, map_size=20, seed=3, prey_alertness=alertness)
    reached = 0
    for _ in range(400):
        env.reset(options={"layout": {"agents": [(9, 9)], "opponents": [(10, 10)]}})
        _step(env, {})
        reached += tuple(env.positions()[1][0]) == (11, 11)
    assert fled[0] <= reached / 400 <= fled[1]


#: The sheep's cells over 40 random steps of one pursuit episode, as the code before
#: ``prey_alertness`` existed (commit 9fa5f8f) played them.
SHEEP_BEFORE = "e5963c2a27a0a0f9a1fb2a482487849b6006000fbfd8dfcd01bdd1c5dd6add93"


@pytest.mark.parametrize(("options", "same"), [({}, True), ({"prey_alertness": 1.0}, True),
                                               ({"prey_alertness": 0.99}, False)])  # fmt: skip
def test_full_alertness_plays_the_episodes_sheep_played_before_the_option(options, same) -> None:
    """The task's sheep draw nothing for their alertness, so every run and model made before
    the option still plays as it did; any lower alertness does draw."""
    env = make("magent/pursuit", agents=(3, 6), map_size=20, seed=5, **options)
    rng = np.random.default_rng(0)
    env.reset(seed=11)
    digest = hashlib.sha256()
    for _ in range(40):
        _step(env, {a: int(rng.integers(env.action_space(a).n)) for a in env.agents})
        digest.update(np.ascontiguousarray(env.positions()[1], dtype=np.int64).tobytes())
    assert (digest.hexdigest() == SHEEP_BEFORE) == same


def test_tiger_pair_attack_rule() -> None:
    # A deer at (1, 1) with tigers at (2, 1) and (1, 2) is walled in and cannot step away.
    env = make("magent/tiger", agents=(2, 3), map_size=10)
    layout = {"layout": {"agents": [(2, 1), (1, 2)], "opponents": [(1, 1)]}}
    env.reset(options=layout)
    both = {"agent_0": env.attack_action(-1, 0), "agent_1": env.attack_action(0, -1)}
    assert _step(env, both)[1] == {"agent_0": 1.0, "agent_1": 1.0}

    env.reset(options=layout)
    assert _step(env, {"agent_0": env.attack_action(-1, 0)})[1] == {"agent_0": 0.0, "agent_1": 0.0}


def test_tiger_three_attackers_score_per_partner() -> None:
    env = make("magent/tiger", agents=(3, 3), map_size=10)
    env.reset(options={"layout": {"agents": [(2, 2), (1, 1), (1, 3)], "opponents": [(1, 2)]}})
    acts = [env.attack_action(-1, 0), env.attack_action(0, 1), env.attack_action(0, -1)]
    rew = _step(env, {f"agent_{i}": a for i, a in enumerate(acts)})[1]
    assert rew == {"agent_0": 2.0, "agent_1": 2.0, "agent_2": 2.0}


def test_tiger_episode_ends_when_every_deer_is_dead() -> None:
    env = make("magent/tiger", agents=(2, 2), map_size=10)
    env.reset(options={"layout": {"agents": [(2, 1), (1, 2)], "opponents": [(1, 1)]}})
    both = {"agent_0": env.attack_action(-1, 0), "agent_1": env.attack_action(0, -1)}
    # hp 5, two hits of 1 a step, +0.2 a step: 3.2, 1.4, dead on the third step.
    for _ in range(2):
        _, rew, term, trunc, _ = env.step(both)
        assert rew == {"agent_0": 1.0, "agent_1": 1.0} and not any(term.values())
    _, _, term, trunc, _ = env.step(both)
    assert all(term.values()) and not any(trunc.values())
    assert env.agents == []


@pytest.mark.parametrize(
    ("positions", "lined_up"),
    [
        ([(3, 5), (4, 5), (5, 5)], True),
        ([(5, 5), (3, 5), (4, 5)], True),
        ([(7, 2), (7, 4), (7, 3), (7, 1)], True),
        ([(3, 5)], True),
        ([(3, 5), (5, 5)], False),
        ([(3, 5), (4, 6)], False),
        ([(3, 5), (4, 5), (4, 6)], False),
        ([(2, 2), (3, 3), (4, 4)], False),
    ],
)
def test_queue_line_detector(positions: list[tuple[int, int]], lined_up: bool) -> None:
    env = make("magent/queue", agents=(1, 4), map_size=10)
    env.reset(options={"layout": {"agents": positions}})
    _, rew, term, *_ = _step(env, {})
    expected = 0.8 if lined_up else -0.2
    assert rew == pytest.approx(dict.fromkeys(env.possible_agents[: len(positions)], expected))
    assert all(term.values()) is lined_up


def test_queue_reward_and_end() -> None:
    env = make("magent/queue", agents=(2, 3), map_size=10)
    env.reset(options={"layout": {"agents": [(3, 5), (5, 5)]}})
    _, rew, term, *_ = _step(env, {})
    assert rew == pytest.approx({"agent_0": -0.2, "agent_1": -0.2})
    assert not any(term.values())
    # agent_0 steps right to (4, 5), next to agent_1 at (5, 5): a row of two.
    right = int(np.flatnonzero((move_offsets(1) == (1, 0)).all(1))[0])
    _, rew, term, *_ = _step(env, {"agent_0": right})
    assert rew == pytest.approx({"agent_0": 0.8, "agent_1": 0.8})
    assert all(term.values()) and env.agents == []

    env = make("magent/queue", agents=(3, 3), map_size=10, end_when_lined_up=False)
    env.reset(options={"layout": {"agents": [(2, 2), (2, 3), (2, 4)]}})
    for _ in range(2):
        _, rew, term, *_ = _step(env, {})
        assert rew == pytest.approx(dict.fromkeys(env.possible_agents, 0.8))
        assert not any(term.values())


@pytest.mark.parametrize(
    ("name", "kwargs"),
    [
        ("magent/pursuit", {"agents": 0}),
        ("magent/pursuit", {"agents": "9-3"}),
        ("magent/pursuit", {"agents": "many"}),
        ("magent/pursuit", {"agents": (10, 5000)}),
        ("magent/tiger", {"agents": 100, "map_size": 20}),
        ("magent/tiger", {"agents": 2, "obstacles": 2500}),
        ("magent/tiger", {"prey_per_agent": 0}),
        ("magent/queue", {"agents": 29}),
        ("magent/queue", {"prey_per_agent": 2.0}),
        ("magent/queue", {"map_size": 4, "agents": 1}),
        ("magent/queue", {"max_steps": 0}),
        ("magent/queue", {"speed": 3}),
        ("magent/pursuit", {"end_when_lined_up": False}),
        ("magent/pursuit", {"render_mode": "human"}),
        ("magent/pursuit", {"prey_alertness": 1.5}),
        ("magent/tiger", {"prey_alertness": 0.5}),
    ],
)
def test_bad_input_raises(name: str, kwargs: dict) -> None:
    with pytest.raises(EnvConfigError):
        make(name, **kwargs)


def test_bad_layout_and_unknown_name_raise() -> None:
    env = make("magent/tiger", agents=(1, 2), map_size=10)
    for layout in (
        {"agents": [(2, 2)], "opponents": [(2, 2)]},
        {"agents": [(0, 2)]},
        {"agents": [(2, 2), (3, 3), (4, 4)]},
        {"agents": []},
    ):
        with pytest.raises(EnvConfigError):
            env.reset(options={"layout": layout})
    with pytest.raises(UnknownEnvError):
        udan.envs.make("magent/battle")
