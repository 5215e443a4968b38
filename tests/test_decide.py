"""The edge's decision step: safety filter, fleet slots, and masking equal to the simulation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from udan.edge.decide import DecisionStep, TaskError, task_of
from udan.edge.fleet import Fleet, FleetState
from udan.edge.safety import STOP, filter_moves
from udan.envs.arena import ArenaBatch, ArenaConfig
from udan.envs.rules import FREE, OBSTACLE, UP, WAIT, WALL, WATER, resolve_moves
from udan.export.runtime import OnnxPolicy
from udan.models import bundled_policy

MODEL = bundled_policy()


# --- safety filter ------------------------------------------------------------------------------
@settings(max_examples=300, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.integers(1, 12),
    st.integers(0, 20),
)
def test_filter_never_two_cars_in_a_cell_nor_swaps(seed: int, cars: int, obstacles: int) -> None:
    rng = np.random.default_rng(seed)
    layout = np.zeros((6, 6), np.uint8)
    cells = rng.permutation(36)
    layout.flat[cells[:obstacles]] = OBSTACLE
    free = cells[obstacles:]
    cars = min(cars, len(free))
    start = free[:cars]
    pos = np.stack([start // 6, start % 6], axis=-1)
    actions = rng.integers(0, 5, cars)
    out = filter_moves(layout, pos, actions)
    moves = np.array([[-1, 0], [1, 0], [0, -1], [0, 1], [0, 0]])
    dest = pos + moves[out.commands]
    assert len({tuple(d) for d in dest}) == cars  # never two cars in one cell
    assert ((dest >= 0) & (dest < 6)).all()  # never off the arena
    assert (layout[dest[:, 0], dest[:, 1]] == FREE).all()  # never into an obstacle
    for i in range(cars):
        for j in range(cars):
            swapped = (dest[i] == pos[j]).all() and (dest[j] == pos[i]).all()
            assert i == j or not swapped
    assert (out.commands[out.blocked] == WAIT).all()
    assert (out.commands[~out.blocked] == actions[~out.blocked]).all()


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 30), st.integers(0, 12))
def test_filter_stops_cars_off_their_cells_and_keeps_out_of_held_cells(
    seed: int, cars: int, held: int
) -> None:
    # cars seen off the cell they were sent to, cells held by things not driven (some off the
    # arena): a stopped car stays and blocks its cell, no car enters a held one, and `dest` is
    # where every command takes its car
    rng = np.random.default_rng(seed)
    layout = np.zeros((6, 6), np.uint8)
    cells = rng.permutation(36)
    layout.flat[cells[:4]] = OBSTACLE
    start = cells[4 : 4 + cars]
    pos = np.stack([start // 6, start % 6], axis=-1)
    actions = rng.integers(0, 5, len(pos))
    expected = np.where(rng.random((len(pos), 1)) < 0.8, pos, rng.integers(-1, 6, (len(pos), 2)))
    others = rng.integers(-1, 7, (held, 2))
    out = filter_moves(layout, pos, actions, expected=expected, others=others)
    stopped = (expected[:, 0] >= 0) & (expected != pos).any(axis=1)
    assert out.stopped.tolist() == stopped.tolist()
    assert (out.commands[stopped] == STOP).all() and not out.blocked[stopped].any()
    moves = np.array([[-1, 0], [1, 0], [0, -1], [0, 1], [0, 0], [0, 0]])  # stop stays too
    assert (out.dest == pos + moves[out.commands]).all()
    assert len({tuple(d) for d in out.dest.tolist()}) == len(pos)
    assert (layout[out.dest[:, 0], out.dest[:, 1]] == FREE).all()
    entered = {tuple(d) for d, p in zip(out.dest.tolist(), pos.tolist(), strict=True) if d != p}
    assert not entered & {tuple(cell) for cell in others.tolist()}
    # and the moves are the rules' own: the stopped cars wait, the held cells are impassable
    passable = layout == FREE
    for row, col in others.tolist():
        if 0 <= row < 6 and 0 <= col < 6:
            passable[row, col] = False
    wanted = np.where(stopped, WAIT, actions)
    rules = resolve_moves(pos[None], wanted[None], passable[None], np.ones((1, len(pos)), bool))
    assert out.dest.tolist() == rules[0].tolist()
    assert out.blocked.tolist() == ((wanted != WAIT) & (rules[0] == pos).all(1)).tolist()


def test_filter_stops_a_car_seen_off_its_cell_and_respects_other_things() -> None:
    layout = np.zeros((3, 3), np.uint8)
    pos = np.array([[1, 1], [2, 2]])
    out = filter_moves(
        layout,
        pos,
        np.array([UP, UP]),
        expected=np.array([[1, 0], [-1, -1]]),
        others=np.array([[1, 2]]),
    )
    assert out.commands.tolist() == [STOP, WAIT]  # car 0 seen off its cell; car 1 blocked
    assert out.stopped.tolist() == [True, False]
    assert out.blocked.tolist() == [False, True]


def test_filter_allows_following() -> None:
    layout = np.zeros((4, 1), np.uint8)
    out = filter_moves(layout, np.array([[1, 0], [2, 0]]), np.array([UP, UP]))
    assert out.commands.tolist() == [UP, UP]


# --- fleet ---------------------------------------------------------------------------------------
def test_fleet_needs_join_and_sighting_and_keeps_slots() -> None:
    fleet = Fleet({1: 11, 2: 12, 3: 13}, lost_s=0.1)
    change = fleet.update({11, 12}, ready={1}, now_ns=0)
    assert change.joined == [1] and fleet.slot == {1: 0} and fleet.fresh == {1}
    # before any step a car that drops out and back in takes its slot again (no memory in it)
    assert fleet.update({11, 12}, ready=set(), now_ns=1_000_000).left == [1]
    assert fleet.update({11, 12}, ready={1}, now_ns=2_000_000).joined == [1]
    assert fleet.slot == {1: 0} and fleet.size == 1
    change = fleet.update({11, 12, 13}, ready={1, 2, 3}, now_ns=10_000_000)
    assert change.joined == [2, 3] and fleet.slot == {1: 0, 2: 1, 3: 2}
    assert fleet.fresh == {1, 2, 3}  # no step yet: car 1 is still new to the policy
    fleet.stepped()
    assert fleet.fresh == set()
    # car 2 stops being seen: it leaves after lost_s, its slot is not reused before a step
    fleet.update({11, 13}, ready={1, 2, 3}, now_ns=50_000_000)
    assert 2 in fleet.slot
    change = fleet.update({11, 13}, ready={1, 2, 3}, now_ns=200_000_000)
    assert change.left == [2] and fleet.slot == {1: 0, 3: 2} and fleet.size == 3
    # it comes back on the next frame: a fresh car, in a new slot (the step has not seen its
    # old one absent yet); a frame later it is still fresh
    fleet.update({11, 12, 13}, ready={1, 2, 3}, now_ns=210_000_000)
    assert fleet.slot[2] == 3 and fleet.fresh == {2}
    fleet.update({11, 12, 13}, ready={1, 2, 3}, now_ns=220_000_000)
    assert fleet.fresh == {2}
    fleet.stepped()
    # the link drops car 1 (silence, LEAVE): it leaves at once; after a step its slot is free
    change = fleet.update({11, 12, 13}, ready={2, 3}, now_ns=230_000_000)
    assert change.left == [1]
    fleet.stepped()
    change = fleet.update({11, 12, 13}, ready={1, 2, 3}, now_ns=240_000_000)
    assert change.joined == [1] and fleet.slot[1] == 0 and fleet.fresh == {1}
    # a car that joins and leaves again between two steps is not new to the next one
    change = fleet.update({11, 12, 13}, ready={2, 3}, now_ns=250_000_000)
    assert change.left == [1] and fleet.fresh == set()


# --- decision step == simulation ---------------------------------------------------------------
def _static_cells(layout: np.ndarray) -> dict[str, frozenset[tuple[int, int]]]:
    kinds = {"obstacle": OBSTACLE, "wall": WALL, "water": WATER}
    return {
        kind: frozenset(map(tuple, np.argwhere(layout == code).tolist()))
        for kind, code in kinds.items()
    }


def test_task_of() -> None:
    assert task_of("arena/find_water") == "find_water"
    with pytest.raises(TaskError, match="magent/pursuit"):
        task_of("magent/pursuit")


@pytest.mark.parametrize(("seed", "rehearse"), [(0, False), (1, False), (2, False), (0, True)])
def test_decision_step_drives_like_the_simulation(seed: int, rehearse: bool) -> None:
    """The edge's masking + policy + safety filter, fed the cells the camera would see, gives
    the same episode as the simulator stepping the same policy on the same layout; and again
    for a second episode after a reset (nothing of the first is remembered). Rehearsing the
    last step before each decision (as the runtime does while a frame is analysed) changes
    nothing."""
    cfg = ArenaConfig(task="find_water", agents=(1, 5), obstacles=(0, 9))
    sim, edge_world = ArenaBatch(cfg, 1, seed=seed), ArenaBatch(cfg, 1, seed=seed)
    reference = OnnxPolicy(MODEL, expected=cfg.spec)
    step = DecisionStep(OnnxPolicy(MODEL, expected=cfg.spec), "find_water", cfg.spec)
    for episode in range(2):
        sim.reset()
        edge_world.reset()
        reference.reset(sim.slots)
        if episode:
            step.reset()
        _drive_one_episode(cfg, sim, edge_world, reference, step, rehearse)


def _drive_one_episode(cfg, sim, edge_world, reference, step, rehearse=False) -> None:
    fresh = np.ones(sim.slots, bool)
    static = _static_cells(edge_world.layout[0])
    slots = {int(s) + 1: int(s) for s in np.flatnonzero(edge_world.present[0])}
    for t in range(cfg.max_steps):
        ref_actions = reference.act(sim.observe()[0], sim.present[0], sim.pos[0], fresh)
        fresh[:] = False
        cells = {car: tuple(edge_world.pos[0, slot]) for car, slot in slots.items()}
        if rehearse:
            step.rehearse()
            step.rehearse()
        decision = step.decide(FleetState(slots, set(slots) if t == 0 else set(), cells, static))
        assert decision.actions.tolist() == ref_actions[list(slots.values())].tolist()
        assert decision.formed == reference.formed == (t % reference.interval == 0)
        sim.step(ref_actions[None])
        commands = np.full(edge_world.slots, WAIT)
        commands[list(slots.values())] = decision.commands
        assert (commands < STOP).all()
        before = edge_world.pos.copy()
        edge_world.step(commands[None])
        # the filtered commands are conflict free: every move the edge sent happened
        moves = np.array([[-1, 0], [1, 0], [0, -1], [0, 1], [0, 0]])
        assert (edge_world.pos == before + moves[commands][None]).all()
    assert np.array_equal(sim.pos, edge_world.pos)
    assert np.array_equal(sim.episode_return, edge_world.episode_return)
    sim_returns = {car: float(sim.episode_return[0, slot]) for car, slot in slots.items()}
    cells = {c: tuple(edge_world.pos[0, s]) for c, s in slots.items()}
    assert step.credit_last_step(slots, cells, static).sum() == edge_world.last_reward[0].sum()
    assert step.returns == pytest.approx(sim_returns)


def test_rehearsing_an_episodes_first_step_changes_nothing() -> None:
    """A new episode has no last step; rehearsing the step its fleet would make from given
    cells (the runtime does, while the first frame is analysed) keeps nothing either."""
    spec = ArenaConfig().spec
    static = {"water": frozenset({(0, 4)}), "obstacle": frozenset({(3, 3)})}
    plain, rehearsed = (
        DecisionStep(OnnxPolicy(MODEL, expected=spec), "find_water", spec) for _ in "ab"
    )
    for step in (plain, rehearsed):  # an episode on 2 slots, then a new one
        step.decide(FleetState({7: 0, 9: 1}, {7, 9}, {7: (6, 4), 9: (8, 8)}, static))
        step.reset()
    assert not rehearsed.rehearse()
    # a fleet in more slots than the step has is not rehearsed: it would grow the step's state
    assert not rehearsed.rehearse({7: 0, 9: 1, 5: 2}, {7: (7, 2), 9: (5, 5), 5: (6, 6)}, static)
    assert len(rehearsed.owner) == 2 and not rehearsed.rehearse({}, {}, static)
    assert rehearsed.rehearse({7: 0, 9: 1}, {7: (7, 2), 9: (5, 5)}, static)
    for t, cells in enumerate([{7: (7, 2), 9: (5, 5)}, {7: (6, 2), 9: (4, 5)}]):
        a, b = (
            step.decide(FleetState({7: 0, 9: 1}, {7, 9} if t == 0 else set(), cells, static))
            for step in (plain, rehearsed)
        )
        assert a.actions.tolist() == b.actions.tolist() and a.formed == b.formed
        assert np.array_equal(plain.policy.h, rehearsed.policy.h)
        assert plain.policy.t == rehearsed.policy.t


def test_a_rehearsal_uses_the_last_step_as_it_was() -> None:
    """Changing the dicts a decision was given, afterwards, changes nothing a rehearsal does."""
    spec = ArenaConfig().spec
    static = {"water": frozenset({(0, 4)})}
    steps = [DecisionStep(OnnxPolicy(MODEL, expected=spec), "find_water", spec) for _ in "ab"]
    decisions = []
    for step in steps:
        slots, cells = {7: 0, 9: 1}, {7: (6, 4), 9: (8, 8)}
        step.decide(FleetState(slots, {7, 9}, cells, static))
        if step is steps[0]:
            slots[3], cells[3] = 6, (0, 0)  # the caller reuses its dicts
            assert step.rehearse()
        decisions.append(
            step.decide(FleetState({7: 0, 9: 1}, set(), {7: (5, 4), 9: (8, 7)}, static))
        )
    a, b = decisions
    assert a.actions.tolist() == b.actions.tolist() and a.formed == b.formed
    assert len(steps[0].owner) == len(steps[1].owner) == 2


def test_decision_step_handles_joins_leaves_and_moving_cars() -> None:
    spec = ArenaConfig().spec
    step = DecisionStep(OnnxPolicy(MODEL, expected=spec), "find_water", spec)
    static = {"water": frozenset({(0, 4)}), "wall": frozenset({(0, 3), (0, 5)})}
    d = step.decide(FleetState({7: 0}, {7}, {7: (6, 4)}, static))
    assert d.cars == (7,) and d.commands.shape == (1,)
    d = step.decide(FleetState({7: 0, 9: 2}, {9}, {7: (6, 4), 9: (8, 8)}, static, moving={7: UP}))
    assert d.cars == (7, 9) and d.commands[0] == WAIT  # a car still moving is not re-commanded
    # a car the guard stopped mid-move is still executing that stop: it holds its cell
    d = step.decide(
        FleetState({7: 0, 9: 2}, set(), {7: (6, 4), 9: (8, 8)}, static, moving={7: STOP})
    )
    assert d.commands[0] == WAIT and d.targets[0].tolist() == [6, 4]
    d = step.decide(FleetState({9: 2}, set(), {9: (8, 8)}, static))
    assert d.cars == (9,)
    d = step.decide(FleetState({8: 0, 9: 2}, {8}, {8: (5, 0), 9: (8, 8)}, static))
    assert d.cars == (8, 9) and step.owner[0] == 8  # car 8 took car 7's slot, fresh
    assert set(step.returns) == {7, 8, 9}  # car 7 keeps what it earned
    d = step.decide(FleetState({}, set(), {}, static))
    assert d.cars == () and d.commands.shape == (0,)


def test_a_steady_fleet_decides_as_one_rebuilt_every_step() -> None:
    """The fleet's slot arrays are kept while the cars keep their slots, and a steady fleet's
    rewards skip the check for new owners: through joins, leaves, a car taking a freed slot, a
    car coming back, fresh flags, rehearsals and the settling of another fleet in between,
    every decision, return and owner equals those of a decision step that rebuilds
    everything each step."""
    spec = ArenaConfig().spec
    static = {"water": frozenset({(0, 4), (0, 6)}), "obstacle": frozenset({(4, 4)})}
    kept, rebuilt = (
        DecisionStep(OnnxPolicy(MODEL, expected=spec), "find_water", spec) for _ in "ab"
    )
    three = {8: 0, 9: 1, 5: 2}
    script = [("decide", {7: 0, 9: 1})] * 6 + [("decide", {7: 0})] * 3
    script += [("decide", {8: 0})] * 4 + [("decide", {8: 0, 9: 1})] * 4 + [("decide", three)] * 6
    script += [("settle", {8: 0, 6: 1, 5: 2}), ("rehearse", None)] + [("decide", three)] * 3
    rng = np.random.default_rng(5)
    last: dict[int, int] = {}
    for t, (what, slots) in enumerate(script):
        if what == "rehearse":
            assert kept.rehearse() and rebuilt.rehearse()
            continue
        cells = {
            car: (int(rng.integers(1, 9)), (int(rng.integers(0, 9)) + 3 * i) % 9)
            for i, car in enumerate(slots)
        }
        if what == "settle":
            a = kept.credit_last_step(dict(slots), dict(cells), static)
            assert a.tolist() == rebuilt.credit_last_step(dict(slots), dict(cells), static).tolist()
            continue
        fresh = {car for car in slots if car not in last} if t % 7 else set(slots)
        rebuilt._fleet_key = rebuilt._owned_key = None
        a = kept.decide(FleetState(dict(slots), set(fresh), dict(cells), static))
        b = rebuilt.decide(FleetState(dict(slots), set(fresh), dict(cells), static))
        assert (a.cars, a.actions.tolist(), a.commands.tolist(), a.rewards.tolist()) == (
            b.cars,
            b.actions.tolist(),
            b.commands.tolist(),
            b.rewards.tolist(),
        )
        assert kept.owner.tolist() == rebuilt.owner.tolist()
        last = slots
    assert kept.returns == rebuilt.returns


def test_a_car_taking_a_slot_starts_with_empty_memory_flagged_fresh_or_not() -> None:
    """A car in a slot another car held gets that car's nothing: its memory starts empty and
    it has no last action, whether or not the caller flagged it fresh."""
    spec = ArenaConfig().spec
    static = {"water": frozenset({(0, 4), (0, 6)})}
    flagged, unflagged = (
        DecisionStep(OnnxPolicy(MODEL, expected=spec), "find_water", spec) for _ in "ab"
    )
    for step in (flagged, unflagged):
        for t, cell in enumerate([(8, 1), (7, 1), (6, 1), (5, 1), (4, 1), (3, 1)]):
            step.decide(
                FleetState({7: 0, 9: 1}, {7, 9} if t == 0 else set(), {7: cell, 9: (8, 8)}, static)
            )
        assert np.abs(step.policy.h[0, 0]).max() > 0  # car 7 remembers something
    a = flagged.decide(FleetState({8: 0, 9: 1}, {8}, {8: (6, 6), 9: (8, 8)}, static))
    b = unflagged.decide(FleetState({8: 0, 9: 1}, set(), {8: (6, 6), 9: (8, 8)}, static))
    assert a.actions.tolist() == b.actions.tolist() and a.stopped == b.stopped == 0
    assert np.array_equal(flagged.policy.h, unflagged.policy.h)
    assert np.array_equal(flagged.policy.q, unflagged.policy.q)
