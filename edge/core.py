"""The control core: what the camera saw, the cars' progress and the clock in; steps out.

Sans-I/O, in the manner of aioquic: no socket, no sleep, no thread and no global time. The
caller (the asyncio shell, :mod:`udan.edge.shell`, or a test) feeds each analysed frame
(:meth:`ControlCore.see`) with the cars the link has ready and the time, asks whether a step is
due (:meth:`ControlCore.due`, with the link's "has this car finished its move"), has it decided
(:meth:`ControlCore.commands_for`), sends the commands itself, and hands back what became of them
(:meth:`ControlCore.dispatched`), which gives the step's telemetry record. The only clock the
core reads is the one it is given, for the decision's timestamp.

When a step is due: on the first frame captured after every car of the fleet finished its move
(so the camera shows where the moves ended) that shows every car, or, if a car is missing from
it, once ``unseen_grace_ns`` has passed since the moves finished (the car is then judged on its
last cell); or when the step period (``step_timeout_ns``) runs out (cars still in a move then get
``wait`` and their destinations are held).

Settling (:class:`MotionRules`): real cars end their moves off their cells' centres. On that
frame, a car farther than the tolerance from its cell's centre or from facing up, or too near a
border to name its cell, is not decided on: :meth:`ControlCore.due` gives a :class:`Recentring`
instead of a step, which sends each such car to the centre of a cell the rules allow (the cell
its last command sent it to if it overlaps it, else the one it stands in, else the nearest free
neighbour; the moves through the same safety filter as the policy's), and the step waits for
those moves and a fresh frame again, for at most ``MotionRules.rounds`` rounds. Every command,
the steps' and the re-centring's, carries the car's measured pose and its target cell's centre
(:class:`udan.edge.protocol.Guidance`), so the car's controller drives from where it is to where
it should be and errors do not add up (docs/motion.md). Real bodies need more
(:mod:`udan.edge.bodies`): a car entering a cell another leaves sideways starts later, a car
entering a cell another leaves is sent its command only once that car accepted its own
(``Decision.after``, honoured by the link), and between steps :meth:`ControlCore.guard` stops a
car about to touch another.

Everything the core consumes can be written down as it comes (a :class:`CoreJournal`, in the
manner of aioquic's QUIC logger): each call's inputs, what the link said about the cars, the
``now`` values and the decision clock. Fed the same entries in the same order, a core with the
same policy and motion rules makes the same decisions, re-centring rounds and guard stops bit
for bit (``udan-edge --replay``, :mod:`udan.edge.replay`); with another policy, the decisions
that policy would have made.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from udan.edge.bodies import Plan, closing_in, corner_delays, crossing
from udan.edge.decide import Decision, DecisionStep
from udan.edge.fleet import Cell, Change, Fleet, FleetState, Seen
from udan.edge.geometry import ArenaGeometry
from udan.edge.protocol import Guidance
from udan.edge.safety import STOP, filter_moves
from udan.envs.rules import ACTION_DELTAS, FREE, WAIT
from udan.profile import move_span

if TYPE_CHECKING:  # data the core reads; it runs neither the link nor the vision
    from udan.edge.link import CommandReport, DispatchReport
    from udan.edge.vision import Scene

#: Rehearse only when the last decision took less than this. A rehearsal runs while the frame
#: is analysed but can hold up its scene by its own length; a decision this long is arithmetic
#: on a large fleet (1,000 agents: ~5 ms warm), not cold caches, and gains little from it.
REHEARSE_UNDER_NS = 3_000_000


@dataclass(frozen=True)
class StepTiming:
    """When the core decides."""

    step_timeout_ns: int = 1_000_000_000
    """Longest a step waits for moves to finish before deciding anyway."""
    unseen_grace_ns: int = 100_000_000
    """Longest a step waits for a car the camera missed (then it is judged on its last cell)."""


class CoreJournal(Protocol):
    """Takes every input of a core as it comes: ``log(call, *inputs)`` with the calls

    - ``start(stepped_ns, timing)``: the clock's first reading, and the step timing;
    - ``see(now, ready, scene)``, ``due(now, moving)`` (the cars the link said had not finished
      their move), ``decide(now, decided_ns, state, decision)`` (the decision clock's reading,
      and the step's fleet state and decision for whoever reads the journal),
      ``dispatched(state_ns, report)``, ``recentred(recentring, report)`` (a re-centring round
      :meth:`ControlCore.due` gave, and its dispatch), ``guard(moving)`` (on the last scene
      seen, while cars move), ``wait_for_moves(now)``, ``new_episode(now)``,
      ``credit_last_step(rewards)`` (on the last scene seen) and ``emergency_stop()``.

    It must be cheap: it runs inside the control step (keep the entries, send them later)."""

    def log(self, call: str, *inputs: Any) -> None: ...


@dataclass(frozen=True)
class MotionRules:
    """How the core keeps real cars on their cells: when a car counts as on its cell, how long
    the core tries to get it there, and how big the cars' bodies are."""

    tolerance_m: float = 0.03
    """A car whose marker is farther than this from its cell's centre is re-centred: with the
    cars' 22 cm bodies on 31 cm cells, two neighbours both this far off towards each other (and
    turned by the heading tolerance) still keep 1 cm apart."""
    heading_tolerance_rad: float = math.radians(5.0)
    """... and so is one turned farther than this from facing up (heading 0)."""
    rounds: int = 3
    """Re-centring rounds before a step decides anyway (on a car that cannot be moved)."""
    geometry: ArenaGeometry = field(default_factory=ArenaGeometry)
    """Where the cells' centres are."""
    body_m: float = 0.22
    """Side of a car's (square) body."""
    guard_horizon_s: float = 0.08
    """How far ahead the guard looks for bodies about to touch: two frames at 40 FPS (the
    frame's analysis and the stop's way to the car) and some."""
    cell_time_s: float = 0.2
    """The cars' time per cell (their controllers' setting; the HIL's mock cars' is
    ``--cell-time-ms``): the guard predicts a commanded move with it, and start delays count
    in it."""
    accel_share: float = 0.25
    """The cars' speed profile: the share of a move's time spent accelerating, as long braking
    (protocol section 8; the mock cars' at every motion level but ``0``)."""
    follow_gap_s: float = 0.04
    """How long after its leader a car that follows it straight (entering the cell it leaves,
    the same way) starts: a slipping leader and a follower setting off together leave the
    guard too little time to see the slip and stop the follower at short cell times
    (docs/motion.md gives the figures)."""

    @property
    def follow_delay(self) -> float:
        """The follow gap in cell times (:func:`udan.edge.bodies.corner_delays`)."""
        return self.follow_gap_s / self.cell_time_s

    def plan(self, guidance: Guidance, taken_ns: int) -> Plan | None:
        """The move a car that took a command with ``guidance`` at ``taken_ns`` drives, as
        its controller plans it (protocol section 8), if the guidance has its measured pose."""
        if guidance.pose is None:
            return None
        (x, y, heading), (tx, ty, th) = guidance.pose, guidance.target
        length = math.hypot(tx - x, ty - y)
        turns = abs(math.remainder(th - heading, math.tau)) / (math.pi / 2)
        span = move_span(length / self.geometry.cell_m, turns)
        return Plan(
            length,
            taken_ns + round(guidance.delay * self.cell_time_s * 1e9),
            round(span * self.cell_time_s * 1e9),
            self.accel_share,
        )

    @property
    def reach(self) -> float:
        """Centres closer than this along both axes: the bodies touch (turned by up to the
        heading tolerance, with a centimetre to spare)."""
        turn = self.heading_tolerance_rad
        return self.body_m * (math.cos(turn) + math.sin(turn)) + 0.01

    def target(self, cell: Cell) -> tuple[float, float, float]:
        """The pose a car on ``cell`` should have: its centre, facing up."""
        return (*self.geometry.cell_centre(*cell), 0.0)


@dataclass(frozen=True)
class Recentring:
    """One round of re-centring, due instead of a step: a command per car of the fleet (wait),
    each with its target (the centre of the cell it is sent to) and measured pose."""

    commands: dict[int, int]
    guidance: dict[int, Guidance]
    cars: tuple[int, ...]
    """The cars off their cells' centres, being re-centred."""
    offsets: dict[int, tuple[float, float]]
    """Each of those: metres from its cell's centre, radians from facing up, as seen."""
    frame: int
    t_capture_ns: int


def _recentring_action(
    layout: np.ndarray,
    cell: Cell,
    xy: tuple[float, float],
    expected: Cell | None,
    held: set[Cell],
    motion: MotionRules,
) -> int:
    """The grid action from ``cell`` (where the car's centre is) to the cell it is re-centred
    into: the cell its last command sent it to when that is this one or a neighbour (a move cut
    short, or a slip, is completed), else this cell, else the free neighbour nearest to it;
    never a cell off the grid, not free in ``layout``, or in ``held``. Wait when none is."""

    def allowed(c: Cell) -> bool:
        rows, cols = layout.shape
        return 0 <= c[0] < rows and 0 <= c[1] < cols and layout[c] == FREE and c not in held

    steps = {tuple(np.add(cell, d).tolist()): a for a, d in enumerate(ACTION_DELTAS.tolist())}
    nearest = sorted(steps, key=lambda c: math.dist(xy, motion.target(c)[:2]))
    order = ([expected] if expected in steps else []) + [cell] + nearest
    return next((steps[c] for c in order if allowed(c)), WAIT)


def _executed_late(command: CommandReport) -> bool:
    """An audit of the car: a command it executed (ACCEPTED, not a duplicate's ack, which
    carries the copy's later receive time) must have reached it by its deadline, judged in the
    car's own clock (the edge-clock estimate is only good to half a round trip)."""
    return (
        command.acked
        and command.result == "accepted"
        and command.car_rx_us is not None
        and command.car_deadline_us is not None
        and command.car_rx_us > command.car_deadline_us
    )


def _late_executions(report: DispatchReport) -> int:
    """Commands of a step that a car executed past their validity (must stay 0)."""
    return sum(_executed_late(r) for r in report.cars.values())


def _late(command: CommandReport) -> bool:
    """The command reached the car after its validity: refused as expired, or executed late."""
    return command.result == "expired" or _executed_late(command)


def _since_us(start_ns: int, t_ns: int | None) -> int | None:
    """Microseconds from ``start_ns`` to ``t_ns`` (None stays None)."""
    return None if t_ns is None else (t_ns - start_ns) // 1000


def _outcome(command: CommandReport) -> str:
    """on_time (the car accepted it in time), missed, or not_ready (nothing was sent)."""
    if command.acked:
        return "on_time"
    return "not_ready" if command.result == "not_ready" else "missed"


class ControlCore:
    """One fleet, one policy step, one clock; see the module docstring."""

    def __init__(
        self,
        fleet: Fleet,
        policy_step: DecisionStep,
        clock: Callable[[], int],
        timing: StepTiming = StepTiming(),
        motion: MotionRules = MotionRules(),
        journal: CoreJournal | None = None,
    ) -> None:
        self.fleet = fleet
        self.policy_step = policy_step
        self.timing = timing
        self.motion = motion
        self._clock = clock
        self._log = None if journal is None else journal.log
        self._rounds = 0  # re-centring rounds since the last step
        self._before: dict[int, Seen] = {}  # each car's sighting before the last one
        self._targets: dict[int, tuple[float, float]] = {}  # where the last commands drive to
        self._plans: dict[int, Plan] = {}  # the moves of the last commands the cars took
        self.static: dict[str, frozenset[Cell]] | None = None  # the last scene's cell markers
        self.uncertain: set[int] = set()  # cars the last scene could not place in a cell
        self.not_before_ns = 0  # frames captured earlier are stale: not analysed
        self.stopped = False  # an emergency stop: no step is decided any more
        self._rehearsed = False  # the last step was rehearsed since the last decision
        self._last_decision_ns = 0  # how long the last decision took (state to commands)
        self._finished_at: int | None = None  # when every car's move was seen finished
        self._stepped_at = clock()  # when the last step was dispatched
        if self._log is not None:
            self._log("start", self._stepped_at, timing)

    # ------------------------------------------------------------------ frames in
    def wants(self, t_capture_ns: int) -> bool:
        """Whether a frame captured at ``t_capture_ns`` is worth analysing (not stale)."""
        return t_capture_ns >= self.not_before_ns

    def see(self, scene: Scene, ready: Iterable[int], now: int) -> Change:
        """Fold one frame's scene and the link's ready cars at ``now`` into the fleet. A car
        seen too near a cell border to name its cell (`uncertain`) keeps its last cell and is
        held by the next step; one never placed yet is not taken into the fleet until it is."""
        if self._log is not None:
            ready = tuple(ready)
            self._log("see", now, ready, scene)
        self.static = scene.cells
        fleet, seen = self.fleet, []
        self.uncertain = set()
        for marker, sighting in scene.cars.items():
            if not sighting.inside:
                continue
            car = fleet.car_of_marker.get(marker)
            if car is not None:
                if car in fleet.pose:
                    self._before[car] = fleet.pose[car]
                fleet.pose[car] = (*sighting.xy, sighting.heading, scene.t_capture_ns)
            if not sighting.uncertain:
                if car is not None:
                    fleet.cell[car] = sighting.cell
            elif car is None or car not in fleet.cell:
                continue
            else:
                self.uncertain.add(car)
            seen.append(marker)
        return fleet.update(seen, ready, now)

    def all_seen(self, scene: Scene) -> bool:
        """Every car of the fleet is on the grid in this frame."""
        markers = self.fleet.markers
        return all(
            (s := scene.cars.get(markers[c])) is not None and s.inside for c in self.fleet.slot
        )

    def _others(self, scene: Scene) -> list[Cell]:
        """Cells of markers on the grid that are not cars of the fleet: they block moves."""
        driven = {self.fleet.markers[c] for c in self.fleet.slot}
        return [s.cell for m, s in scene.cars.items() if s.inside and m not in driven]

    # ------------------------------------------------------------------ rehearsal
    def warm_up(self, finished: Callable[[int], bool]) -> None:
        """While a frame is analysed: if it may be the deciding one (every car finished its
        move) and the last decision was short, rehearse the step (caches warmed; see
        :meth:`udan.edge.decide.DecisionStep.rehearse`)."""
        if (
            self._last_decision_ns < REHEARSE_UNDER_NS
            and bool(self.fleet.slot)
            and all(map(finished, self.fleet.slot))
            and self._rehearse()
        ):
            self._rehearsed = True

    def _rehearse(self) -> bool:
        """The last step once more; before an episode's first step, the step its fleet would
        make from the cells and markers seen last (that first step is otherwise the coldest:
        1.2 ms median in the full loop, against 0.6 ms for a rehearsed one)."""
        if self.policy_step.rehearse():
            return True
        slots = dict(self.fleet.slot)
        cell = self.fleet.cell
        if self.static is None or not all(car in cell for car in slots):
            return False
        return self.policy_step.rehearse(slots, {car: cell[car] for car in slots}, self.static)

    # ------------------------------------------------------------------ steps
    def due(
        self, scene: Scene, finished: Callable[[int], bool], now: int
    ) -> FleetState | Recentring | None:
        """The fleet as the step to decide now sees it, a re-centring round to dispatch first,
        or None when neither is due on this frame (see the module docstring); ``finished``
        tells whether a car ended its move."""
        fleet = self.fleet
        if self.stopped or not fleet.slot:
            if self._log is not None:
                self._log("due", now, ())
            return None
        moving = fleet.moving(finished)
        if self._log is not None:
            self._log("due", now, tuple(moving))
        if not moving and self._finished_at is None:
            self._finished_at = now
        finished_at = self._finished_at
        fresh_view = finished_at is not None and scene.t_capture_ns >= finished_at
        # a car the camera missed in this frame would be judged on a stale cell (and stopped
        # for the step): wait a few frames for it, not longer (it may have left the arena)
        waited = finished_at is not None and now - finished_at > self.timing.unseen_grace_ns
        fresh_view = fresh_view and (self.all_seen(scene) or waited)
        timed_out = now - self._stepped_at > self.timing.step_timeout_ns
        if not (fresh_view or timed_out):
            return None
        if fresh_view and scene.calibrated and self._rounds < self.motion.rounds:
            off = self.unsettled(scene)
            if off:
                self._rounds += 1
                return self._recentring(scene, off)
        self._rounds = 0
        # an uncalibrated frame (calibration markers hidden, the camera knocked) places no car
        doubted = self.uncertain if scene.calibrated else fleet.slot.keys()
        held = {c: WAIT for c in doubted if c in fleet.slot and c not in moving}
        return fleet.snapshot(
            scene.cells,
            self._others(scene),
            {**moving, **held},
            scene.frame_index,
            scene.t_capture_ns,
            frozenset(held),
            scene.calibrated,
        )

    # ------------------------------------------------------------------ settling
    def unsettled(self, scene: Scene) -> dict[int, tuple[float, float]]:
        """Cars of the fleet this frame shows off their cells' centres (beyond the tolerance,
        or too near a border to name the cell) -> (metres off, radians off facing up)."""
        rules, markers, off = self.motion, self.fleet.markers, {}
        for car in self.fleet.slot:
            s = scene.cars.get(markers[car])
            if s is None or not s.inside:
                continue
            distance, turned = math.hypot(*s.offset), abs(math.remainder(s.heading, math.tau))
            if s.uncertain or distance > rules.tolerance_m or turned > rules.heading_tolerance_rad:
                off[car] = (distance, turned)
        return off

    def _recentring(self, scene: Scene, off: Mapping[int, tuple[float, float]]) -> Recentring:
        """Send each car in ``off`` to the centre of a cell the rules allow, through the safety
        filter; every other car waits where it is (its command keeps it alive and centred)."""
        fleet, markers = self.fleet, self.fleet.markers
        cars = sorted(fleet.slot)
        sighted = {c: s for c in cars if (s := scene.cars.get(markers[c])) is not None and s.inside}
        here = {c: sighted[c].cell if c in sighted else fleet.cell.get(c) for c in cars}
        layout, _ = self.policy_step.layout(scene.cells)
        others = self._others(scene)
        held = set(others) | {cell for c, cell in here.items() if c not in off}
        actions = {c: WAIT for c in cars}
        for car in off:
            s = sighted[car]
            expected = self.policy_step.expected_cell(fleet.slot[car])
            actions[car] = _recentring_action(layout, s.cell, s.xy, expected, held, self.motion)
            held.add(tuple(np.add(s.cell, ACTION_DELTAS[actions[car]]).tolist()))
        placed = [c for c in cars if here[c] is not None]
        filtered = filter_moves(
            layout,
            np.array([here[c] for c in placed], np.int64).reshape(-1, 2),
            np.array([actions[c] for c in placed], np.int64),
            others=others,
        )
        dest = dict(zip(placed, map(tuple, filtered.dest.tolist()), strict=True))
        paths = {
            car: (sighted[car].xy, self.motion.target(dest[car])[:2]) for car in off if car in dest
        }
        standing = {car: s.xy for car, s in sighted.items() if car not in paths}
        crossed = crossing(paths, standing, self.motion.reach)  # they wait for the next round
        guidance = {}
        for car in placed:
            cell = dest[car]
            taken = any(here[c] == cell for c in placed if c != car)
            if car not in sighted or taken or car in crossed:  # it stays as it is, this round
                continue
            guidance[car] = self._guide(cell, fleet.pose.get(car))
            if car in off:
                self.policy_step.redirect(fleet.slot[car], cell)
        commands = dict.fromkeys(cars, WAIT)
        fleet.command.update(commands)
        self._targets = {car: g.target[:2] for car, g in guidance.items()}
        return Recentring(
            commands=commands,
            guidance=guidance,
            cars=tuple(sorted(off)),
            offsets=dict(off),
            frame=scene.frame_index,
            t_capture_ns=scene.t_capture_ns,
        )

    def _guide(self, cell: Cell, seen: Seen | None, delay: float = 0.0) -> Guidance:
        """A command's target (``cell``'s centre, facing up), the car's measured pose, and how
        long (cell times) it waits before it starts."""
        if seen is None:
            return Guidance(self.motion.target(cell), delay=delay)
        return Guidance(self.motion.target(cell), seen[:3], seen[3], delay)

    def guard(self, scene: Scene, finished: Callable[[int], bool]) -> dict[int, int]:
        """Between steps, on every frame: a stop for each car whose body is about to touch
        another's (:func:`udan.edge.bodies.closing_in`: a leader that slipped and stands short,
        a car stopped mid-move in another's path); empty when all is well."""
        moving = self.fleet.moving(finished)
        if not moving or self.stopped:
            return {}
        if self._log is not None:
            self._log("guard", tuple(moving))
        t = scene.t_capture_ns
        fleet = self.fleet
        now = {c: (x, y) for c, (x, y, _, at) in fleet.pose.items() if at == t and c in fleet.slot}
        before = {
            c: (x, y, (t - at) / 1e9) for c, (x, y, _, at) in self._before.items() if c in moving
        }
        targets = {c: self._targets[c] for c in moving if c in self._targets and c in now}
        plans = {c: self._plans[c] for c in targets if c in self._plans}
        motion = self.motion
        stops = closing_in(now, before, targets, motion.guard_horizon_s, motion.reach, plans, t)
        for car in stops:
            del self._targets[car]
            self._plans.pop(car, None)
        commands = dict.fromkeys(sorted(stops), STOP)
        fleet.command.update(commands)
        return commands

    def recentred(self, recentring: Recentring, report: DispatchReport) -> dict[str, Any]:
        """What became of a re-centring round's commands; its telemetry record. A round in
        which no car sent to a centre got its command does not count against the rounds: it
        did not try (the link drops a car that stays silent, so this cannot go on for ever)."""
        if self._log is not None:
            self._log("recentred", recentring, report)
        self.fleet.command.update(recentring.commands)
        self._took(recentring.guidance, report)
        sent = [report.cars[c] for c in recentring.cars if c in recentring.guidance]
        if sent and not any(r.acked for r in sent):
            self._rounds -= 1
        return {
            "t_ns": report.decision_ns,
            "frame": recentring.frame,
            "round": self._rounds,
            "cars": list(recentring.cars),
            "offsets": {
                str(c): [round(d * 1000, 1), round(math.degrees(h), 2)]
                for c, (d, h) in recentring.offsets.items()
            },
            "on_time": report.on_time,
            "missed": report.missed,
            "not_ready": report.not_ready,
            "late_sends": report.late_sends,
            "late_executions": _late_executions(report),
            "outcomes": {str(c): _outcome(r) for c, r in report.cars.items()},
        }

    def _took(self, guidance: Mapping[int, Guidance], report: DispatchReport) -> None:
        """The moves the guard predicts: each car that took its command drives its plan from
        when it took it (its receive time, else when its ACK came)."""
        self._plans = {}
        for car, g in guidance.items():
            r = report.cars.get(car)
            taken = None if r is None or not r.acked else r.car_received_ns or r.acked_ns
            plan = None if taken is None else self.motion.plan(g, taken)
            if plan is not None:
                self._plans[car] = plan

    # ------------------------------------------------------------------ steps
    def commands_for(self, state: FleetState, now: int) -> tuple[Decision, dict[int, int], int]:
        """The step's decision (with each command's guidance: the car's measured pose and its
        target cell's centre), each car's command, and the decision's time (the commands'
        validity counts from it); ``now`` is when the state was taken."""
        decision = self.policy_step.decide(state)
        commands = {c: int(a) for c, a in zip(decision.cars, decision.commands, strict=True)}
        targets = dict(zip(decision.cars, map(tuple, decision.targets.tolist()), strict=True))
        moves = {
            car: (state.cells[car], targets[car] if commands[car] < WAIT else state.cells[car])
            for car in decision.cars
            if car not in state.moving
        }
        delays, waits = corner_delays(moves, straight=self.motion.follow_delay)
        leaving = {start: car for car, (start, end) in moves.items() if start != end}
        after = {
            car: leaving[end]
            for car, (start, end) in moves.items()
            if start != end and end in leaving and car not in waits
        }
        for car in waits:  # a ring of bodies: nobody of it can go first
            commands[car], targets[car] = WAIT, state.cells[car]
            self.policy_step.redirect(state.slots[car], state.cells[car])
        guidance = {
            car: self._guide(targets[car], state.poses.get(car), delays.get(car, 0.0))
            for car in decision.cars
        }
        decision = replace(decision, guidance=guidance, after=after)
        self._targets = {car: g.target[:2] for car, g in guidance.items()}
        self.fleet.stepped()
        decided_ns = self._clock()
        self._last_decision_ns = decided_ns - now
        if self._log is not None:
            self._log("decide", now, decided_ns, state, decision)
        return decision, commands, decided_ns

    def dispatched(
        self,
        state: FleetState,
        decision: Decision,
        commands: dict[int, int],
        report: DispatchReport,
        state_ns: int,
    ) -> dict[str, Any]:
        """What became of a step's commands; returns the step's telemetry record: spans and
        counts, and per car (keyed by its id as a string) its cell, heading, command, outcome,
        sends, with the policy's groups (car ids, leader first) and the episode's score so far.
        The live view, the annotated video and the flight recorder read this same record."""
        if self._log is not None:
            self._log("dispatched", state_ns, report)
        decided_ns = report.decision_ns
        rehearsed, self._rehearsed = self._rehearsed, False
        self.fleet.command.update(commands)
        # a car still in its move was sent its destination again: its move is not that plan
        self._took({c: g for c, g in decision.guidance.items() if c not in state.moving}, report)
        cars = report.cars.values()
        received = [r.car_received_ns for r in cars if r.acked]
        late = _late_executions(report)
        acked = [r.acked_ns for r in cars if r.acked]
        every = len(commands)
        returns = self.policy_step.returns
        return {
            "t_ns": decided_ns,
            "step": self.policy_step.t,
            "cars": len(state.slots),
            "fresh": sorted(state.fresh),  # new to the policy: their memory starts empty
            "frame": state.frame,
            "state_to_commands_ns": decided_ns - state_ns,
            "commands_to_received_ns": max(received) - decided_ns
            if len(received) == every
            else None,
            "frame_to_received_ns": max(received) - state.t_capture_ns
            if len(received) == every
            else None,
            "decision_to_acked_ns": max(acked) - decided_ns if len(acked) == every else None,
            "on_time": report.on_time,
            "retried": report.retried,
            "missed": report.missed,
            "not_ready": report.not_ready,
            "slow_sends": report.slow_sends,
            "late_sends": report.late_sends,
            "late_executions": late,
            "moving": sum(c not in state.uncertain for c in state.moving),  # period ran out
            "uncertain": len(state.uncertain),
            "uncertain_cars": sorted(state.uncertain),
            "uncalibrated": int(not state.calibrated),
            "blocked": decision.blocked,
            "stopped": decision.stopped,
            "spans_ns": decision.spans_ns,
            "formed": decision.formed,
            "rehearsed": rehearsed,
            "outcomes": {str(c): _outcome(r) for c, r in report.cars.items()},
            "commands": {str(c): a for c, a in commands.items()},
            "offsets": self._offsets(state),
            "sends": {str(c): r.attempts for c, r in report.cars.items()},
            "after": {str(c): leader for c, leader in decision.after.items()},
            "timeline_us": {
                str(c): [
                    _since_us(decided_ns, t)
                    for t in (r.first_sent_ns, r.car_received_ns, r.acked_ns)
                ]
                for c, r in report.cars.items()
            },
            "late_cars": sorted(c for c, r in report.cars.items() if _late(r)),
            "cells": {str(c): list(cell) for c, cell in state.cells.items()},
            "headings_deg": {
                str(c): round(math.degrees(pose[2]), 1) for c, pose in state.poses.items()
            },
            "groups": self.policy_step.groups(),
            "score": sum(returns.values()) / len(returns) if returns else None,
        }

    def _offsets(self, state: FleetState) -> dict[str, list[float]]:
        """Per car the step decides on and saw in its frame: [mm from its cell's centre,
        degrees from facing up] (docs/motion.md: what the HIL report plots). A car the step
        holds (still in a move when the step period ran out, or uncertain) is left out: the
        policy does not act on it."""
        out = {}
        for car, (x, y, heading, taken_ns) in state.poses.items():
            if taken_ns != state.t_capture_ns or car not in state.cells or car in state.moving:
                continue
            cx, cy, _ = self.motion.target(state.cells[car])
            off = math.hypot(x - cx, y - cy)
            out[str(car)] = [
                round(off * 1000, 1),
                round(math.degrees(math.remainder(heading, math.tau)), 2),
            ]
        return out

    def wait_for_moves(self, now: int) -> None:
        """The step is done (dispatched, the pause after it taken): the next one waits for the
        moves it started."""
        if self._log is not None:
            self._log("wait_for_moves", now)
        self._finished_at = None
        self._stepped_at = now

    # ------------------------------------------------------------------ episodes, stop
    def new_episode(self, now: int) -> None:
        """A new episode: no car, empty memories, frames captured before ``now`` are stale."""
        if self._log is not None:
            self._log("new_episode", now)
        self.policy_step.reset()
        self._rehearsed = False
        self._rounds = 0
        self._targets = {}
        self._plans = {}
        self.fleet.reset()
        self.not_before_ns = now

    def credit_last_step(self, scene: Scene) -> np.ndarray | None:
        """The rewards of the step that just ended, credited without deciding again (the end
        of an episode), from a frame that shows every car; None if this one does not."""
        rewards = None
        if self.all_seen(scene):
            slots = dict(self.fleet.slot)
            cells = {c: self.fleet.cell[c] for c in slots}
            rewards = self.policy_step.credit_last_step(slots, cells, scene.cells)
        if self._log is not None:
            self._log("credit_last_step", rewards)
        return rewards

    def emergency_stop(self) -> None:
        """No step is decided any more (the caller stops the cars)."""
        if self._log is not None:
            self._log("emergency_stop")
        self.stopped = True
