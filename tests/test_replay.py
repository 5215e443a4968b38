"""The core's journal, as the recorder writes it, fed back to a new core: the same decisions
bit for bit with the same policy, the differences listed with another; no file, no process
(tests/test_recording.py has those)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import pytest
from test_core import (
    MARKER_CAR,
    MARKERS,
    MS,
    STATIC,
    TIMING,
    Clock,
    all_acked,
    busy,
    done,
    scene,
)

from udan.edge import flightlog as fl
from udan.edge.core import ControlCore, MotionRules, Recentring
from udan.edge.decide import DecisionStep
from udan.edge.fleet import Fleet
from udan.edge.recorder import Writer
from udan.edge.replay import ReplayError, check_model, replay_decisions
from udan.envs.arena import ArenaConfig
from udan.export.runtime import OnnxPolicy
from udan.models import bundled_policy

# the core's own test scaffolding (tests/test_core.py) builds the scenes and dispatch reports
SPEC = ArenaConfig(task="find_water").spec
QMIX = bundled_policy().parents[1] / "baselines" / "find_water_qmix" / "policy.onnx"


class _Collect:
    """Stands in for the recorder's file and frame taker: keeps what the writer writes."""

    def __init__(self) -> None:
        self.messages: list[tuple[str, dict[str, Any]]] = []
        self.wanted: list[tuple[int, int]] = []

    def write(self, topic: str, log_time: int, body: dict[str, Any], sequence: int = 0) -> None:
        self.messages.append((topic, json.loads(json.dumps(body))))  # through JSON, as a file

    def want(self, index: int, t_capture_ns: int) -> None:
        self.wanted.append((index, t_capture_ns))


class _Journal:
    """The loop's side of the recorder without the outlet: entries straight to the writer."""

    def __init__(self) -> None:
        self.out = _Collect()
        self.writer = Writer(self.out, self.out)
        self.seq = 0

    def log(self, call: str, *inputs: Any) -> None:
        self.writer.take(("core", self.seq, call, inputs))
        self.seq += 1

    def flight_log(self) -> fl.FlightLog:
        entries = [fl.entry_of(topic, body) for topic, body in self.out.messages]
        meta = {
            "fleet": [{"id": c, "marker": m} for c, m in MARKERS.items()],
            "lost_s": 0.5,
            "task": "find_water",
            "model_sha256": "",
            "motion": dataclasses.asdict(MotionRules()),
        }
        entries = sorted((e for e in entries if e is not None), key=lambda e: e.seq)
        return fl.FlightLog(Path("journal"), meta, entries)


def _step(policy: OnnxPolicy) -> DecisionStep:
    return DecisionStep(policy, "find_water", SPEC)


def _run(core: ControlCore, clock: Clock) -> list[dict[str, Any]]:
    """Two episodes with what a run meets: cars joining, a car the camera misses, a car too
    near a border, a car off its cell's centre (re-centred first), the step period running out
    on a moving car (the guard watching meanwhile), a car leaving; returns the step records."""
    records = []
    cells = {11: (8, 1), 12: (8, 4), 13: (8, 7)}
    for episode in range(2):
        core.new_episode(clock.ns)
        for k in range(14):
            clock.ns += 40 * MS
            shown = dict(cells)
            if k == 5:
                shown.pop(13)  # the camera misses car 3 in this frame
            if k == 9 and episode == 1:
                shown.pop(12)
                ready = [1, 3]  # car 2 left (its link dropped)
            else:
                ready = [1, 2, 3]
            frame = scene(clock.ns, shown, STATIC, index=100 * episode + k,
                          uncertain=[11] if k == 7 else (),
                          offsets={12: (0.05, 0.0)} if k == 2 else None)  # fmt: skip
            core.see(frame, ready, clock.ns)
            finished = busy if k in (3, 4) else done  # a move that runs past the period
            state = core.due(frame, finished, clock.ns)
            if state is None:
                core.guard(frame, finished)
                continue
            if isinstance(state, Recentring):
                core.recentred(state, all_acked(state.commands, clock.ns))
                core.wait_for_moves(clock.ns)
                continue
            state_ns = clock.ns
            clock.ns += MS
            decision, commands, decided = core.commands_for(state, state_ns)
            records.append(
                core.dispatched(state, decision, commands, all_acked(commands, decided), state_ns)
            )
            for car, action in commands.items():  # the cars do what they are told, roughly
                r, c = cells[{v: k for k, v in MARKER_CAR.items()}[car]]
                dr, dc = {0: (-1, 0), 1: (1, 0), 2: (0, -1), 3: (0, 1)}.get(action, (0, 0))
                if 0 <= r + dr < 9 and 0 <= c + dc < 9:
                    cells[MARKERS[car]] = (r + dr, c + dc)
            clock.ns += MS
            core.wait_for_moves(clock.ns)
        frame = scene(clock.ns, cells, STATIC, index=100 * episode + 99)
        core.see(frame, [1, 3], clock.ns)
        core.credit_last_step(frame)
    core.emergency_stop()
    return records


@pytest.fixture(scope="module")
def recorded() -> tuple[fl.FlightLog, list[dict[str, Any]], list[tuple[int, int]]]:
    policy = OnnxPolicy(bundled_policy(), expected=SPEC)
    journal, clock = _Journal(), Clock()
    core = ControlCore(Fleet(MARKERS, lost_s=0.5), _step(policy), clock, TIMING, journal=journal)
    records = _run(core, clock)
    return journal.flight_log(), records, journal.out.wanted


def test_the_recorded_journal_replays_to_the_same_decisions(recorded):
    log, records, wanted = recorded
    assert len(records) > 15
    # every decision asked the recorder for its frame
    assert len(wanted) == len(records)
    result = replay_decisions(log, _step(OnnxPolicy(bundled_policy(), expected=SPEC)))
    assert result["steps"] == len(records)
    assert result["identical"] == result["steps"] and result["differences"] == []
    assert result["steps_not_recorded"] == 0 and result["journal_gaps"] == 0
    # the re-centring rounds (car 2 off its cell's centre) and the guard's checks too
    assert result["recentring_rounds"] >= 2
    assert result["recentring_identical"] == result["recentring_rounds"]
    assert any(e.call == "guard" for e in log.entries)


def test_a_changed_input_shows_as_a_differing_decision(recorded):
    log, _, _ = recorded
    entries = [fl.Entry(e.seq, e.call, json.loads(json.dumps(e.message))) for e in log.entries]
    decisions = [k for k, e in enumerate(entries) if e.call == "decide"]
    # the scene the sixth decision was taken on shows car 1 a cell further right
    k = decisions[5]
    see = next(e for e in reversed(entries[:k]) if e.call == "see")
    car = next(s for s in see.message["cars"] if s["marker"] == 11)
    car["cell"] = [car["cell"][0], min(car["cell"][1] + 1, 8)]
    changed = fl.FlightLog(log.path, log.meta, entries)
    result = replay_decisions(changed, _step(OnnxPolicy(bundled_policy(), expected=SPEC)))
    # the decisions before it are as recorded; it, or one after it, is not
    assert result["differing"] >= 1
    assert min(d.get("step", d.get("after_step")) for d in result["differences"]) >= 6


def test_another_policy_shows_what_it_would_have_decided(recorded):
    log, _, _ = recorded
    result = replay_decisions(log, _step(OnnxPolicy(QMIX, expected=SPEC)))
    assert result["steps"] == len([e for e in log.entries if e.call == "decide"])
    assert result["differing"] > 0 and result["commands_differing"] > 0
    first = next(d for d in result["differences"] if "round" not in d)
    assert set(first) == {"step", "frame", "cars", "actions"}


def test_a_model_for_another_task_is_refused(recorded):
    log, _, _ = recorded
    with pytest.raises(ReplayError, match="plays surround; the recording journal is of"):
        check_model(log, "surround", bundled_policy())
    assert check_model(log, "find_water", bundled_policy()) is False  # not the recorded file
