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
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from udan.edge.decide import Decision, DecisionStep
from udan.edge.fleet import Cell, Change, Fleet, FleetState
from udan.envs.rules import WAIT

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


def _late(command: CommandReport) -> bool:
    """The command reached the car after its validity: refused as expired, or (an audit that
    must never fire) accepted after its deadline in the car's own clock."""
    if command.result == "expired":
        return True
    return (
        command.acked
        and command.result == "accepted"
        and command.car_rx_us is not None
        and command.car_deadline_us is not None
        and command.car_rx_us > command.car_deadline_us
    )


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
    ) -> None:
        self.fleet = fleet
        self.policy_step = policy_step
        self.timing = timing
        self._clock = clock
        self.static: dict[str, frozenset[Cell]] | None = None  # the last scene's cell markers
        self.uncertain: set[int] = set()  # cars the last scene could not place in a cell
        self.not_before_ns = 0  # frames captured earlier are stale: not analysed
        self.stopped = False  # an emergency stop: no step is decided any more
        self._rehearsed = False  # the last step was rehearsed since the last decision
        self._last_decision_ns = 0  # how long the last decision took (state to commands)
        self._finished_at: int | None = None  # when every car's move was seen finished
        self._stepped_at = clock()  # when the last step was dispatched

    # ------------------------------------------------------------------ frames in
    def wants(self, t_capture_ns: int) -> bool:
        """Whether a frame captured at ``t_capture_ns`` is worth analysing (not stale)."""
        return t_capture_ns >= self.not_before_ns

    def see(self, scene: Scene, ready: Iterable[int], now: int) -> Change:
        """Fold one frame's scene and the link's ready cars at ``now`` into the fleet. A car
        seen too near a cell border to name its cell (`uncertain`) keeps its last cell and is
        held by the next step; one never placed yet is not taken into the fleet until it is."""
        self.static = scene.cells
        fleet, seen = self.fleet, []
        self.uncertain = set()
        for marker, sighting in scene.cars.items():
            if not sighting.inside:
                continue
            car = fleet.car_of_marker.get(marker)
            if not sighting.uncertain:
                if car is not None:
                    fleet.cell[car] = sighting.cell
                    fleet.heading[car] = sighting.heading
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
    def due(self, scene: Scene, finished: Callable[[int], bool], now: int) -> FleetState | None:
        """The fleet as the step to decide now sees it, or None when no step is due on this
        frame (see the module docstring); ``finished`` tells whether a car ended its move."""
        fleet = self.fleet
        if self.stopped or not fleet.slot:
            return None
        moving = fleet.moving(finished)
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

    def commands_for(self, state: FleetState, now: int) -> tuple[Decision, dict[int, int], int]:
        """The step's decision, each car's command, and the decision's time (the commands'
        validity counts from it); ``now`` is when the state was taken."""
        decision = self.policy_step.decide(state)
        self.fleet.stepped()
        decided_ns = self._clock()
        self._last_decision_ns = decided_ns - now
        commands = {c: int(a) for c, a in zip(decision.cars, decision.commands, strict=True)}
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
        decided_ns = report.decision_ns
        rehearsed, self._rehearsed = self._rehearsed, False
        self.fleet.command.update(commands)
        cars = report.cars.values()
        received = [r.car_received_ns for r in cars if r.acked]
        # an audit of the car: a command it executed (ACCEPTED, not a duplicate's ack, which
        # carries the copy's later receive time) must have reached it by its deadline, judged
        # in the car's own clock (the edge-clock estimate is only good to half a round trip)
        late = sum(
            r.car_rx_us > r.car_deadline_us for r in cars if r.acked and r.result == "accepted"
        )
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
            "sends": {str(c): r.attempts for c, r in report.cars.items()},
            "late_cars": sorted(c for c, r in report.cars.items() if _late(r)),
            "cells": {str(c): list(cell) for c, cell in state.cells.items()},
            "headings_deg": {str(c): round(math.degrees(h), 1) for c, h in state.headings.items()},
            "groups": self.policy_step.groups(),
            "score": sum(returns.values()) / len(returns) if returns else None,
        }

    def wait_for_moves(self, now: int) -> None:
        """The step is done (dispatched, the pause after it taken): the next one waits for the
        moves it started."""
        self._finished_at = None
        self._stepped_at = now

    # ------------------------------------------------------------------ episodes, stop
    def new_episode(self, now: int) -> None:
        """A new episode: no car, empty memories, frames captured before ``now`` are stale."""
        self.policy_step.reset()
        self._rehearsed = False
        self.fleet.reset()
        self.not_before_ns = now

    def credit_last_step(self, scene: Scene) -> np.ndarray | None:
        """The rewards of the step that just ended, credited without deciding again (the end
        of an episode), from a frame that shows every car; None if this one does not."""
        if not self.all_seen(scene):
            return None
        slots = dict(self.fleet.slot)
        cells = {c: self.fleet.cell[c] for c in slots}
        return self.policy_step.credit_last_step(slots, cells, scene.cells)

    def emergency_stop(self) -> None:
        """No step is decided any more (the caller stops the cars)."""
        self.stopped = True
