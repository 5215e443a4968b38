"""The control core on its own: scenes, the link's ready and finished cars and a clock go in,
steps come out; no socket, no thread, no real clock. The policy is the bundled find_water model
(real masking, grouping, inference and safety filter)."""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterable, Mapping

import numpy as np
import pytest

from udan.edge.core import ControlCore, MotionRules, Recentring, StepTiming
from udan.edge.decide import DecisionStep
from udan.edge.fleet import Fleet, FleetState
from udan.edge.geometry import ArenaGeometry
from udan.edge.link import CommandReport, DispatchReport
from udan.edge.protocol import Guidance
from udan.edge.vision import CarSighting, Scene
from udan.envs.arena import ArenaConfig
from udan.envs.rules import WAIT
from udan.export.runtime import OnnxPolicy
from udan.models import bundled_policy
from udan.profile import travelled

MODEL = bundled_policy()
MS = 1_000_000
MARKERS = {1: 11, 2: 12, 3: 13}
MARKER_CAR = {m: c for c, m in MARKERS.items()}
STATIC = {
    "obstacle": frozenset({(4, 2)}),
    "wall": frozenset(),
    "water": frozenset({(0, 1), (0, 4), (0, 7)}),
}
TIMING = StepTiming(step_timeout_ns=1000 * MS, unseen_grace_ns=100 * MS)
GEOMETRY = ArenaGeometry()


class Clock:
    """The time the core reads for its decisions; tests set it."""

    def __init__(self) -> None:
        self.ns = 0

    def __call__(self) -> int:
        return self.ns


@pytest.fixture(scope="module")
def policy() -> OnnxPolicy:
    return OnnxPolicy(MODEL, expected=ArenaConfig(task="find_water").spec)


@pytest.fixture
def clock() -> Clock:
    return Clock()


def make_core(policy: OnnxPolicy, clock: Clock, motion: MotionRules | None = None) -> ControlCore:
    spec = ArenaConfig(task="find_water").spec
    step = DecisionStep(policy, "find_water", spec)
    return ControlCore(Fleet(MARKERS, lost_s=0.5), step, clock, TIMING, motion or MotionRules())


@pytest.fixture
def core(policy: OnnxPolicy, clock: Clock) -> ControlCore:
    return make_core(policy, clock)


def scene(
    t_ns: int,
    cells: Mapping[int, tuple[int, int]],
    static: Mapping = STATIC,
    index: int = 0,
    uncertain: Iterable[int] = (),
    calibrated: bool = True,
    offsets: Mapping[int, tuple[float, float]] | None = None,
    headings: Mapping[int, float] | None = None,
) -> Scene:
    """A frame at ``t_ns`` showing marker -> cell (on its centre, facing up, unless
    ``offsets`` (metres) and ``headings`` (radians) say otherwise); markers in ``uncertain``
    too near a border to name their cell."""
    doubted, offsets, headings = set(uncertain), offsets or {}, headings or {}
    cars = {}
    for m, cell in cells.items():
        dx, dy = offsets.get(m, (0.0, 0.0))
        cx, cy = GEOMETRY.cell_centre(*cell)
        inside = min(cell) >= 0 and max(cell) < 9
        xy, heading = (cx + dx, cy + dy), headings.get(m, 0.0)
        cars[m] = CarSighting(m, cell, xy, heading, (dx, dy), inside, m in doubted)
    return Scene(t_ns, index, calibrated, cars, dict(static), 0)


def all_acked(
    commands: Mapping[int, int], decided_ns: int, missed: Iterable[int] = ()
) -> DispatchReport:
    """What the link reports when every car but ``missed`` accepted its command in 1 ms."""
    reports = {}
    for car, action in commands.items():
        r = CommandReport(car, action, attempts=1, first_sent_ns=decided_ns)
        if car not in missed:
            r.acked, r.acked_ns, r.car_received_ns, r.result = (
                True,
                decided_ns + MS,
                decided_ns + MS // 2,
                "accepted",
            )
            r.car_deadline_us, r.car_rx_us = 10_000, 500
        reports[car] = r
    report = DispatchReport(decided_ns, decided_ns + 10 * MS, reports)
    report.on_time = sum(r.acked for r in reports.values())
    report.missed = len(reports) - report.on_time
    return report


def step(core: ControlCore, clock: Clock, state: FleetState, missed: Iterable[int] = ()) -> dict:
    """Decide on ``state`` now, dispatch as the link would, and start waiting for the moves."""
    state_ns = clock.ns
    clock.ns += MS  # the decision takes a millisecond
    decision, commands, decided_ns = core.commands_for(state, state_ns)
    assert decided_ns == clock.ns
    record = core.dispatched(
        state, decision, commands, all_acked(commands, decided_ns, missed), state_ns
    )
    clock.ns += MS
    core.wait_for_moves(clock.ns)
    return record


def done(_car: int) -> bool:
    return True


def busy(_car: int) -> bool:
    return False


TWO = {11: (8, 1), 12: (8, 5)}  # cars 1 and 2, by marker


def see(
    core: ControlCore,
    clock: Clock,
    at_ms: int,
    cells: Mapping[int, tuple[int, int]],
    ready: set[int],
    captured_ms: int | None = None,
) -> Scene:
    """At ``at_ms``, the scene of a frame captured at ``captured_ms`` (default: then) folded
    into the core with the link's ``ready`` cars."""
    clock.ns = at_ms * MS
    frame = scene((at_ms if captured_ms is None else captured_ms) * MS, cells)
    core.see(frame, ready=ready, now=clock.ns)
    return frame


def first_step(
    core: ControlCore, clock: Clock, cells: Mapping = TWO, missed: Iterable[int] = ()
) -> dict:
    """Every car of ``cells`` joined and seen at 0 ms, and the first step dispatched."""
    frame = see(core, clock, 0, cells, ready={MARKER_CAR[m] for m in cells})
    return step(core, clock, core.due(frame, done, clock.ns), missed)


def test_a_car_that_joins_and_is_seen_is_decided_for_as_new(
    core: ControlCore, clock: Clock
) -> None:
    frame = scene(0, TWO)
    change = core.see(frame, ready={1}, now=0)
    assert change.joined == [1]  # car 2 is seen but has not joined over the link
    state = core.due(frame, done, 0)
    assert state is not None and state.slots == {1: 0} and state.fresh == {1}
    assert state.cells == {1: (8, 1)} and state.others == [(8, 5)]  # car 2 blocks a cell
    record = step(core, clock, state)
    assert record["fresh"] == [1] and record["cars"] == 1 and set(record["commands"]) == {"1"}
    assert record["outcomes"] == {"1": "on_time"}
    # car 2 joins: it takes the next slot with fresh memory, car 1 is no longer new
    frame = scene(300 * MS, TWO)
    assert core.see(frame, ready={1, 2}, now=300 * MS).joined == [2]
    state = core.due(frame, done, 300 * MS)
    assert state is not None and state.slots == {1: 0, 2: 1} and state.fresh == {2}
    assert step(core, clock, state)["fresh"] == [2]


def test_a_car_the_link_drops_leaves_and_its_last_command_is_forgotten(
    core: ControlCore, clock: Clock
) -> None:
    first_step(core, clock)
    assert set(core.fleet.command) == {1, 2}
    frame = scene(300 * MS, TWO)
    change = core.see(frame, ready={1}, now=300 * MS)  # LEAVE, reboot or silence
    assert change.left == [2] and set(core.fleet.command) == {1}
    state = core.due(frame, done, 300 * MS)
    assert state.slots == {1: 0} and state.others == [(8, 5)]  # now a thing the edge does not drive
    assert set(step(core, clock, state)["commands"]) == {"1"}


def test_a_car_the_camera_misses_is_waited_for_then_judged_on_its_last_cell_then_lost(
    core: ControlCore, clock: Clock
) -> None:
    first_step(core, clock)
    missing = see(core, clock, 200, {11: (7, 1)}, ready={1, 2})
    assert core.due(missing, done, clock.ns) is None  # moves finished now: wait for car 2
    missing = see(core, clock, 250, {11: (7, 1)}, ready={1, 2})
    assert core.due(missing, done, clock.ns) is None  # within the grace
    missing = see(core, clock, 310, {11: (7, 1)}, ready={1, 2})
    state = core.due(missing, done, clock.ns)  # grace over: decided on its last cell
    assert state is not None and state.cells == {1: (7, 1), 2: (8, 5)}
    step(core, clock, state)
    clock.ns += 500 * MS  # unseen for longer than lost_s: it leaves the fleet
    change = core.see(scene(clock.ns, {11: (7, 1)}), ready={1, 2}, now=clock.ns)
    assert change.left == [2] and set(core.fleet.slot) == {1}


def test_stale_frames_decide_nothing(core: ControlCore, clock: Clock) -> None:
    first_step(core, clock, {11: (8, 1)})
    # the moves end at 200 ms; a frame captured before that still shows them under way
    early = see(core, clock, 200, {11: (8, 1)}, ready={1}, captured_ms=190)
    assert core.due(early, done, clock.ns) is None
    later = see(core, clock, 215, {11: (7, 1)}, ready={1}, captured_ms=210)
    assert core.due(later, done, clock.ns).cells == {1: (7, 1)}
    # a new episode: frames captured before it are not even analysed
    core.new_episode(300 * MS)
    assert not core.wants(299 * MS) and core.wants(300 * MS)
    assert core.fleet.slot == {} and core.policy_step.t == 0


def test_when_the_step_period_runs_out_moving_cars_wait_and_missed_commands_are_reported(
    core: ControlCore, clock: Clock
) -> None:
    first = first_step(core, clock, missed={2})
    assert first["outcomes"] == {"1": "on_time", "2": "missed"} and first["missed"] == 1
    assert first["commands_to_received_ns"] is None  # not every car received its command
    assert first["state_to_commands_ns"] == MS
    car1_doing = int(first["commands"]["1"])

    def only_2_done(car: int) -> bool:
        return car == 2

    frame = see(core, clock, 500, TWO, ready={1, 2})
    assert core.due(frame, only_2_done, clock.ns) is None  # car 1 is still in its move
    frame = see(core, clock, 1010, TWO, ready={1, 2})  # the step period ran out
    state = core.due(frame, only_2_done, clock.ns)
    assert state is not None and dict(state.moving) == {1: car1_doing}
    record = step(core, clock, state)
    assert record["commands"]["1"] == WAIT  # told to wait; its move's destination is held


def test_the_safety_filter_vetoes_a_move_into_a_cell_something_else_holds(
    core: ControlCore, clock: Clock
) -> None:
    # car 1 stands in the bottom-left corner, things the edge does not drive on both its
    # neighbours: the policy (which does not see them) moves, the filter says no
    frame = see(core, clock, 0, {11: (8, 0), 20: (7, 0), 21: (8, 1)}, ready={1})
    state = core.due(frame, done, 0)
    assert sorted(state.others) == [(7, 0), (8, 1)]
    decision, commands, _ = core.commands_for(state, 0)
    assert decision.actions[0] != WAIT  # the policy wanted a move ...
    assert commands == {1: WAIT} and decision.blocked == 1  # ... and it was held back


def test_an_emergency_stop_ends_the_steps(core: ControlCore, clock: Clock) -> None:
    frame = see(core, clock, 0, {11: (8, 1)}, ready={1})
    assert core.due(frame, done, 0) is not None
    core.emergency_stop()
    frame = see(core, clock, 5000, {11: (8, 1)}, ready={1})
    assert core.due(frame, done, clock.ns) is None
    assert core.due(frame, busy, clock.ns) is None  # not even when the period ran out


def test_the_last_step_is_credited_only_from_a_frame_that_shows_every_car(
    core: ControlCore, clock: Clock
) -> None:
    first_step(core, clock, {11: (1, 1), 12: (8, 5)})
    assert core.credit_last_step(scene(clock.ns, {11: (0, 1)})) is None
    rewards = core.credit_last_step(scene(clock.ns, {11: (1, 1), 12: (8, 5)}))
    assert rewards.tolist() == [1.0, 0.0]  # car 1 ended in front of a water source
    assert core.policy_step.returns == {1: 1.0, 2: 0.0}


def test_an_uncertain_car_is_held_on_its_last_cell_and_counted(
    policy: OnnxPolicy, clock: Clock
) -> None:
    """A car seen too near a cell border to name its cell, once re-centring has had its rounds
    (none here), keeps the cell it was last placed in and is told to wait (its command's
    target is that cell's centre), the others are decided as usual; the step record counts
    it."""
    core = make_core(policy, clock, MotionRules(rounds=0))
    first_step(core, clock)
    clock.ns = 300 * MS
    frame = scene(clock.ns, {11: (7, 1), 12: (8, 6)}, uncertain=[12])
    core.see(frame, ready={1, 2}, now=clock.ns)
    state = core.due(frame, done, clock.ns)
    assert state.cells == {1: (7, 1), 2: (8, 5)}  # not the guessed (8, 6)
    assert state.uncertain == {2} and state.moving[2] == WAIT
    state_ns = clock.ns
    decision, commands, _ = core.commands_for(state, state_ns)
    assert commands[2] == WAIT
    assert decision.guidance[2].target == (*GEOMETRY.cell_centre(8, 5), 0.0)
    record = core.dispatched(state, decision, commands, all_acked(commands, clock.ns), state_ns)
    core.wait_for_moves(clock.ns)
    assert record["commands"]["2"] == WAIT and record["uncertain"] == 1
    assert record["uncertain_cars"] == [2]
    # placed with confidence again: decided from its new cell
    clock.ns = 600 * MS
    frame = scene(clock.ns, {11: (7, 1), 12: (8, 6)})
    core.see(frame, ready={1, 2}, now=clock.ns)
    state = core.due(frame, done, clock.ns)
    assert state.cells[2] == (8, 6) and not state.uncertain and 2 not in state.moving


def test_a_car_never_placed_with_confidence_does_not_join(core: ControlCore, clock: Clock) -> None:
    frame = scene(0, TWO, uncertain=[12])
    change = core.see(frame, ready={1, 2}, now=0)
    assert change.joined == [1] and 2 not in core.fleet.cell
    frame = scene(50 * MS, TWO)
    assert core.see(frame, ready={1, 2}, now=50 * MS).joined == [2]


def test_an_uncalibrated_frame_holds_every_car_and_says_why(
    core: ControlCore, clock: Clock
) -> None:
    """The calibration markers hidden: the frame places no car, so after the grace the step
    holds every car on its last cell instead of commanding it, and the record says so."""
    first_step(core, clock)
    for at_ms in (300, 410):
        clock.ns = at_ms * MS
        frame = scene(clock.ns, {}, calibrated=False)
        core.see(frame, ready={1, 2}, now=clock.ns)
        state = core.due(frame, done, clock.ns)
    assert state is not None and not state.calibrated and state.uncertain == {1, 2}
    record = step(core, clock, state)
    assert record["commands"] == {"1": WAIT, "2": WAIT} and record["uncalibrated"] == 1


def expected(core: ControlCore, car: int) -> tuple[int, int]:
    """Where the last step sent ``car``."""
    cell = core.policy_step.expected_cell(core.fleet.slot[car])
    assert cell is not None
    return cell


def centre(cell: tuple[int, int]) -> tuple[float, float, float]:
    return (*GEOMETRY.cell_centre(*cell), 0.0)


def test_every_command_carries_the_cars_measured_pose_and_its_target_centre(
    core: ControlCore, clock: Clock
) -> None:
    frame = scene(0, TWO, offsets={12: (0.012, -0.004)}, headings={12: 0.03})
    core.see(frame, ready={1, 2}, now=0)
    state = core.due(frame, done, 0)
    assert isinstance(state, FleetState)
    decision, _, _ = core.commands_for(state, 0)
    for car, cell in zip(decision.cars, decision.targets.tolist(), strict=True):
        guide = decision.guidance[car]
        assert guide.target == centre(tuple(cell)) and guide.captured_ns == 0
        assert guide.delay == 0.0  # two cars far apart: nobody waits for anybody
    x, y = GEOMETRY.cell_centre(8, 5)
    assert decision.guidance[2].pose == (x + 0.012, y - 0.004, 0.03)


def test_a_car_off_its_cells_centre_is_recentred_before_the_policy_acts(
    core: ControlCore, clock: Clock
) -> None:
    """Within the tolerance a car is decided on; beyond it, a re-centring round comes first
    (every car waits, the one off is sent to the centre of the cell it is in), and the policy
    decides only once the camera shows it back."""
    first_step(core, clock)
    here = {11: expected(core, 1), 12: expected(core, 2)}
    t = core.policy_step.t
    frame = see(core, clock, 300, here, ready={1, 2})
    frame = scene(clock.ns, here, offsets={11: (0.02, 0.01), 12: (0.05, 0.0)})
    core.see(frame, ready={1, 2}, now=clock.ns)
    due = core.due(frame, done, clock.ns)
    assert isinstance(due, Recentring) and due.cars == (2,) and core.policy_step.t == t
    assert due.commands == {1: WAIT, 2: WAIT}
    assert due.guidance[2].target == centre(here[12])
    assert due.guidance[2].pose[:2] == pytest.approx(np.add(centre(here[12])[:2], (0.05, 0.0)))
    assert due.guidance[1].target == centre(here[11])  # within the tolerance: it just waits
    record = core.recentred(due, all_acked(due.commands, clock.ns))
    assert record["cars"] == [2] and record["offsets"] == {"2": [50.0, 0.0]}
    assert record["on_time"] == 2
    core.wait_for_moves(clock.ns)
    assert core.due(frame, busy, clock.ns + MS) is None  # the re-centring moves are under way
    frame = see(core, clock, 450, here, ready={1, 2})
    state = core.due(frame, done, clock.ns)
    assert isinstance(state, FleetState) and state.cells == {1: here[11], 2: here[12]}
    assert step(core, clock, state)["stopped"] == 0  # where the edge sent them: no veto


def test_a_car_turned_beyond_the_heading_tolerance_is_recentred(
    core: ControlCore, clock: Clock
) -> None:
    frame = scene(0, TWO, headings={11: 0.2})  # 11.5 degrees
    core.see(frame, ready={1, 2}, now=0)
    due = core.due(frame, done, 0)
    assert isinstance(due, Recentring) and due.cars == (1,)
    assert due.offsets[1] == pytest.approx((0.0, 0.2))
    assert due.guidance[1].target == centre((8, 1))  # facing up again


def test_a_car_stopped_across_a_border_goes_on_to_the_cell_its_command_sent_it_to(
    core: ControlCore, clock: Clock
) -> None:
    """Stopped half-way from (8, 5) up to (7, 5), seen too near the border to name its cell:
    not held, but re-centred into (7, 5), which the edge had reserved for it; and if something
    stands there now, back into (8, 5). Either way the step that follows does not stop it."""
    first_step(core, clock)
    core.policy_step.redirect(core.fleet.slot[2], (7, 5))  # its last command: up
    across = {11: expected(core, 1), 12: (8, 5)}
    frame = scene(300 * MS, across, offsets={12: (0.0, -0.15)}, uncertain=[12])
    core.see(frame, ready={1, 2}, now=300 * MS)
    due = core.due(frame, done, 300 * MS)
    assert isinstance(due, Recentring) and due.cars == (2,)
    assert due.guidance[2].target == centre((7, 5))
    core.recentred(due, all_acked(due.commands, 300 * MS))
    core.wait_for_moves(301 * MS)
    frame = see(core, clock, 400, {11: expected(core, 1), 12: (7, 5)}, ready={1, 2})
    state = core.due(frame, done, clock.ns)
    assert isinstance(state, FleetState) and step(core, clock, state)["stopped"] == 0
    # the same stop with a marker of something else on (7, 5): back to where it came from
    core.policy_step.redirect(core.fleet.slot[2], (7, 5))
    blocked = {**across, 30: (7, 5)}
    frame = scene(900 * MS, blocked, offsets={12: (0.0, -0.15)}, uncertain=[12])
    core.see(frame, ready={1, 2}, now=900 * MS)
    due = core.due(frame, done, 900 * MS)
    assert isinstance(due, Recentring) and due.guidance[2].target == centre((8, 5))


def test_recentring_gives_up_after_its_rounds_and_the_policy_decides(
    core: ControlCore, clock: Clock
) -> None:
    """A car that cannot be moved (a stuck wheel) is not re-centred for ever: after
    ``rounds`` rounds the policy decides, here on the cell it is seen in."""
    dues = []
    for i in range(core.motion.rounds + 1):
        clock.ns = i * 100 * MS
        frame = scene(clock.ns, TWO, offsets={12: (0.06, 0.0)})
        core.see(frame, ready={1, 2}, now=clock.ns)
        dues.append(core.due(frame, done, clock.ns))
        core.wait_for_moves(clock.ns)
    assert [type(d) for d in dues] == [Recentring] * core.motion.rounds + [FleetState]


def test_the_guard_stops_a_car_closing_in_on_one_stopped_short_and_only_that_one(
    policy: OnnxPolicy, clock: Clock
) -> None:
    """Car 1 drives up into (7, 1) behind car 2, which slipped: it stands 12 cm short of its
    own target (6, 1), its body still across (7, 1). Car 1 keeps coming at its speed: the
    guard stops it (car 2 is not closing in: it is not moving); while car 2 is out of the
    way, the same approach is left alone."""
    core = make_core(policy, clock)
    cells = {11: (8, 1), 12: (7, 1)}
    core.see(scene(0, cells), ready={1, 2}, now=0)
    state = core.due(scene(0, cells), done, 0)
    core.commands_for(state, 0)
    core._targets = {1: centre((7, 1))[:2], 2: centre((6, 1))[:2]}  # both sent up
    core.fleet.command.update({1: 0, 2: 0})
    cell = GEOMETRY.cell_m

    def car1_at(t_ms: int, offset_up: float, car2: tuple[int, int], car2_up: float) -> Scene:
        frame = scene(
            t_ms * MS, {11: (8, 1), 12: car2}, offsets={11: (0, -offset_up), 12: (0, -car2_up)}
        )
        core.see(frame, ready={1, 2}, now=t_ms * MS)
        return frame

    def only_1_moving(car: int) -> bool:
        return car != 1

    car1_at(0, 0.0, (7, 1), 0.12)
    frame = car1_at(25, 0.3 * cell, (7, 1), 0.12)  # 0.3 of a cell in 25 ms, car 2 still
    assert core.guard(frame, only_1_moving) == {1: 5}
    assert core.fleet.command[1] == 5  # the stop is its last command: its move has ended
    core._targets = {1: centre((7, 1))[:2]}
    core.fleet.command[1] = 0
    car1_at(50, 0.0, (5, 1), 0.0)
    frame = car1_at(75, 0.3 * cell, (5, 1), 0.0)
    assert core.guard(frame, only_1_moving) == {}


def test_the_guard_stops_a_car_in_its_start_delay_before_it_drives_into_a_slipped_leaver(
    policy: OnnxPolicy, clock: Clock
) -> None:
    """Car 2 leaves (7, 1) to the right, car 1 enters (7, 1) from below a cell time later
    (cells of 200 ms). Car 2 slips: it keeps half its plan's pace and stops half-way, across
    the corner of car 1's way. The guard predicts each commanded move by its plan at the pace
    the car kept: car 1, not moving yet, is stopped on the frame that shows car 2's move over,
    before it sets off (speeds alone see a standing car 1); after a move without a slip,
    nobody is stopped."""
    motion = MotionRules(cell_time_s=0.2)
    cell = GEOMETRY.cell_m

    def run(pace: float) -> list[dict[int, int]]:
        core = make_core(policy, clock, motion)
        cells = {11: (8, 1), 12: (7, 1)}
        core.see(scene(0, cells), ready={1, 2}, now=0)
        core.commands_for(core.due(scene(0, cells), done, 0), 0)
        guidance = {
            1: Guidance(centre((7, 1)), centre((8, 1)), 0, delay=1.0),
            2: Guidance(centre((7, 2)), centre((7, 1)), 0),
        }
        core._targets = {car: g.target[:2] for car, g in guidance.items()}
        core._took(guidance, all_acked({1: 0, 2: 3}, 0))
        core.fleet.command.update({1: 0, 2: 3})
        stops = []
        for t_ms in (125, 150, 175, 200, 225):
            right = pace * cell * float(travelled((t_ms - 0.5) / 200, motion.accel_share))
            frame = scene(t_ms * MS, cells, offsets={12: (right, 0.0)})
            core.see(frame, ready={1, 2}, now=t_ms * MS)
            stops.append(core.guard(frame, lambda car, t=t_ms: car == 2 and t >= 200))
        return stops

    assert run(0.5) == [{}, {}, {}, {1: 5}, {}]
    assert run(1.0) == [{}] * 5


def test_a_recentring_round_whose_commands_all_missed_does_not_count(
    core: ControlCore, clock: Clock
) -> None:
    """The rounds bound a car that cannot be moved, not a link that lost the commands."""
    dues = []
    for i in range(core.motion.rounds + 2):
        clock.ns = i * 100 * MS
        frame = scene(clock.ns, TWO, offsets={12: (0.06, 0.0)})
        core.see(frame, ready={1, 2}, now=clock.ns)
        due = core.due(frame, done, clock.ns)
        dues.append(due)
        if isinstance(due, Recentring):
            core.recentred(due, all_acked(due.commands, clock.ns, missed=[2] if i < 2 else []))
        core.wait_for_moves(clock.ns)
    assert [type(d) for d in dues] == [Recentring] * (core.motion.rounds + 2)


def test_the_step_record_says_where_each_car_is_what_it_was_told_and_the_groups(
    core: ControlCore, clock: Clock
) -> None:
    """What the live view, the video and the recorder draw from: per car its cell, heading,
    command, outcome and sends, the groups as car ids (leader first), the score so far."""
    cells = {11: (8, 1), 12: (8, 2), 13: (7, 1)}
    headings = {11: 0.0, 12: math.radians(3), 13: -math.radians(4)}  # within the tolerance
    frame = scene(0, cells)
    frame.cars.update(
        {m: dataclasses.replace(s, heading=headings[m]) for m, s in frame.cars.items()}
    )
    core.see(frame, ready={1, 2, 3}, now=0)
    record = step(core, clock, core.due(frame, done, 0), missed={3})
    assert record["cells"] == {"1": [8, 1], "2": [8, 2], "3": [7, 1]}
    assert record["headings_deg"] == {"1": 0.0, "2": 3.0, "3": -4.0}
    assert record["sends"] == {"1": 1, "2": 1, "3": 1}
    assert record["outcomes"]["3"] == "missed" and record["late_cars"] == []
    policy = core.policy_step.policy
    assert record["groups"] and len(record["groups"]) == len(policy.groups)
    car_of_slot = {slot: car for car, slot in core.fleet.slot.items()}
    for group, slots in zip(record["groups"], policy.groups.tolist(), strict=True):
        assert group == [car_of_slot[s] for s in slots]  # leader first, as formed
    assert record["score"] == 0.0  # no step has ended yet
    json.dumps(record)  # the telemetry file, the live view and the recorder take it as is


def test_a_command_refused_as_expired_is_late_for_that_car(core: ControlCore, clock: Clock):
    frame = see(core, clock, 0, TWO, ready={1, 2})
    state = core.due(frame, done, clock.ns)
    decision, commands, decided_ns = core.commands_for(state, clock.ns)
    report = all_acked(commands, decided_ns, missed={2})
    report.cars[2].result = "expired"
    record = core.dispatched(state, decision, commands, report, clock.ns)
    assert record["late_cars"] == [2] and record["late_executions"] == 0
