"""Replaying a flight recording: ``udan-edge --replay run.mcap [--model B] [--vision]``.

**Decisions.** A new :class:`~udan.edge.core.ControlCore`, with the recorded fleet's cars and
markers, the recorded step timing and motion rules, is fed the recorded journal entry by entry
(:mod:`udan.edge.flightlog`): each scene with the link's ready cars and its ``now``, each step
check with the cars the link said were still moving, each decision with the decision clock's
recorded reading, each dispatch report (of a step or of a re-centring round), each guard check,
each episode start and end. No camera, no car and no clock of this machine takes part. With the
recorded model, every decision comes out the same, bit for bit (actions, commands after the
safety filter, rewards, blocked and stopped counts, whether groups formed, each command's target
and start delay and the car it waits for), and so does every re-centring round (its cars,
commands and targets); any that does not is reported. With another model (``--model B``, for the
same task), each step shows what B would have decided in the situation the recorded model's
commands had led to: a step-by-step shadow, not a run of B (its commands would have moved the
cars elsewhere).

**Vision** (``--vision``). The vision is run again on the recorded frames, in order: each frame
is analysed as the camera's next one, and again (up to a sweep of the whole image) while a car
of the fleet is not tracked or the camera model is not fitted, since recorded frames come a few
a second, not 40. Its sightings are compared with the ones recorded for the same frame: the
same cell, how far apart (millimetres) and turned (degrees) the poses are, cars found in one and
not the other. Lossless (decided) frames and lossy (JPEG) ones are counted apart.
"""

from __future__ import annotations

import hashlib
import math
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from udan.edge import flightlog as fl
from udan.edge.camera import Frame
from udan.edge.core import ControlCore, MotionRules, Recentring
from udan.edge.decide import Decision, DecisionStep
from udan.edge.fleet import Fleet, FleetState
from udan.edge.geometry import ArenaGeometry
from udan.edge.perception import VisionSettings
from udan.edge.vision import Scene, Vision


class ReplayError(ValueError):
    """A replay that cannot be made (a model for another task); one line."""


def file_sha256(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def check_model(log: fl.FlightLog, task: str, model: Path) -> bool:
    """Whether ``model`` is the recorded one; a `ReplayError` if it drives another task."""
    recorded = log.meta.get("task")
    if recorded != task:
        raise ReplayError(f"model {model} plays {task}; the recording {log.path} is of {recorded}")
    return file_sha256(model) == log.meta.get("model_sha256")


# -- decisions --------------------------------------------------------------------------------
def _same(recorded: dict[str, Any], decision: Decision) -> bool:
    again = fl.decided(decision)
    return all(recorded.get(key) == value for key, value in again.items())


def _difference(step: int, recorded: dict[str, Any], decision: Decision | None) -> dict:
    out: dict[str, Any] = {"step": step, "frame": recorded["frame"]}
    if decision is None:
        out["replayed"] = "no step was due"
        return out
    commands = dict(zip(decision.cars, decision.commands.tolist(), strict=True))
    out["cars"] = {
        str(car): {"recorded": old, "replayed": commands.get(car)}
        for car, old in zip(recorded["cars"], recorded["commands"], strict=True)
        if commands.get(car) != old
    }
    out["actions"] = {"recorded": recorded["actions"], "replayed": decision.actions.tolist()}
    return out


def _finished(moving: list[int]) -> Callable[[int], bool]:
    """The link's answer as recorded: a car finished its move unless it was listed moving."""
    still = frozenset(moving)
    return lambda car: car not in still


@dataclass
class _Now:
    """The clock the replayed core reads: the recorded decision clock, set before each call."""

    ns: int = 0

    def __call__(self) -> int:
        return self.ns


def motion_rules(log: fl.FlightLog) -> MotionRules:
    """The recorded motion rules (settling tolerances, bodies, the cells' geometry)."""
    recorded = dict(log.meta["motion"])
    return MotionRules(**{**recorded, "geometry": ArenaGeometry(**recorded["geometry"])})


def _same_round(recorded: dict[str, Any], recentring: Recentring) -> bool:
    return (
        recorded["cars_off"] == list(recentring.cars)
        and recorded["commands"] == {str(c): a for c, a in recentring.commands.items()}
        and recorded["guidance"] == fl.guidance_json(recentring.guidance)
    )


def replay_decisions(log: fl.FlightLog, policy_step: DecisionStep) -> dict[str, Any]:
    """Feed the recorded journal to a new core around ``policy_step``; each decision and each
    re-centring round compared with the recorded one."""
    entries = log.entries
    start = next(e.message for e in entries if e.call == "start")
    fleet_file = log.meta["fleet"]
    fleet = Fleet({c["id"]: c["marker"] for c in fleet_file}, lost_s=log.meta["lost_s"])
    clock = _Now(start["now_ns"])
    core = ControlCore(fleet, policy_step, clock, log.timing, motion_rules(log))
    scene: Scene | None = None
    state: FleetState | None = None
    recentring: Recentring | None = None
    decision: Decision | None = None
    commands: dict[int, int] = {}
    steps = identical = commands_differing = rounds = rounds_identical = 0
    differences: list[dict[str, Any]] = []
    unexpected = 0  # steps or rounds the replay made where the recording did not
    for k, entry in enumerate(entries):
        m = entry.message
        call = entry.call
        if call == "see":
            scene = fl.scene_of(m)
            core.see(scene, m["ready"], m["now_ns"])
        elif call == "due":
            due = core.due(scene, _finished(m["moving"]), m["now_ns"])
            state = due if isinstance(due, FleetState) else None
            recentring = due if isinstance(due, Recentring) else None
            recorded = entries[k + 1].call if k + 1 < len(entries) else None
            unexpected += state is not None and recorded != "decide"
            unexpected += recentring is not None and recorded != "recentred"
        elif call == "decide":
            steps += 1
            if state is None:
                differences.append(_difference(steps, m, None))
                decision = None
                continue
            clock.ns = m["decided_ns"]
            decision, commands, _ = core.commands_for(state, m["now_ns"])
            if _same(m, decision):
                identical += 1
            else:
                commands_differing += sum(
                    dict(zip(m["cars"], m["commands"], strict=True)).get(c) != a
                    for c, a in commands.items()
                )
                differences.append(_difference(steps, m, decision))
        elif call == "dispatched":
            if state is not None and decision is not None:
                core.dispatched(state, decision, commands, fl.report_of(m), m["state_ns"])
            state = decision = None
        elif call == "recentred":
            rounds += 1
            where = {"round": rounds, "after_step": steps, "frame": m["frame"]}
            if recentring is None:
                differences.append({**where, "replayed": "no re-centring round was due"})
                continue
            if _same_round(m, recentring):
                rounds_identical += 1
            else:
                differences.append(
                    {**where, "recorded": m["cars_off"], "replayed": list(recentring.cars)}
                )
            core.recentred(recentring, fl.report_of(m))
            recentring = None
        elif call == "guard" and scene is not None:
            core.guard(scene, _finished(m["moving"]))
        elif call == "wait_for_moves":
            core.wait_for_moves(m["now_ns"])
        elif call == "new_episode":
            core.new_episode(m["now_ns"])
        elif call == "credit_last_step" and scene is not None:
            core.credit_last_step(scene)
        elif call == "emergency_stop":
            core.emergency_stop()
    return {
        "steps": steps,
        "identical": identical,
        "identical_share": round(identical / steps, 6) if steps else None,
        "differing": steps - identical,
        "commands_differing": commands_differing,
        "recentring_rounds": rounds,
        "recentring_identical": rounds_identical,
        "steps_not_recorded": unexpected,
        "journal_gaps": log.gaps(),
        "differences": differences,
    }


# -- vision -----------------------------------------------------------------------------------
def vision_settings(log: fl.FlightLog, folder: Path) -> VisionSettings:
    """The recorded vision settings, the calibration taken from the recording's attachment."""
    recorded = log.meta["vision"]
    calibration = None
    if log.calibration is not None:
        calibration = folder / fl.CALIBRATION_ATTACHMENT
        calibration.write_bytes(log.calibration)
    return VisionSettings(
        ArenaGeometry(**recorded["geometry"]),
        None if recorded["car_markers"] is None else tuple(recorded["car_markers"]),
        None if calibration is None else str(calibration),
        {int(m): h for m, h in recorded["marker_heights"].items()},
    )


def _settle(vision: Vision, image: np.ndarray, t_ns: int, index: int) -> tuple[Scene, int]:
    """The frame analysed as the next one, and again while the camera model is unfitted, a car
    of the fleet untracked, or a track not found in this frame (a car that moved further than
    its track's window since the last recorded frame): at most one sweep more. The last scene
    and the next index."""
    scene = vision.process(Frame(image, t_ns, index))
    for _ in range(vision.sweep_frames):
        tracker = vision.tracker
        found = all(track.index == index for track in tracker.tracks.values())
        if vision.calibrated and found and not tracker.missing():
            break
        index += 1
        scene = vision.process(Frame(image, t_ns, index))
    return scene, index + 1


def _spread(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p99": None, "max": None}
    a = np.asarray(values)
    return {
        "p50": round(float(np.median(a)), 3),
        "p99": round(float(np.percentile(a, 99)), 3),
        "max": round(float(a.max()), 3),
    }


STILL_WIDTH = 960
"""Width of ``--still``'s picture."""


def draw_still(
    image: np.ndarray, vision: Vision, recorded: list[dict[str, Any]], scene: Scene
) -> np.ndarray:
    """A recorded frame with each recorded sighting's cell outlined (green where the vision
    again agrees, red where not) and its marker and cell written beside it; `STILL_WIDTH`
    wide."""
    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    cell_m = vision.geometry.cell_m
    for sighting in recorded:
        row, col = sighting["cell"]
        square = np.array([[col, row], [col + 1, row], [col + 1, row + 1], [col, row + 1]])
        corners = vision.fit.to_image(square * cell_m).astype(np.int32)
        again = scene.cars.get(sighting["marker"])
        colour = (
            (40, 200, 40) if again is not None and list(again.cell) == [row, col] else (40, 40, 230)
        )
        cv2.polylines(out, [corners], True, colour, max(2, image.shape[0] // 300))
        x, y = corners.min(0)
        label = f"{sighting['marker']}: {row},{col}"
        size = image.shape[0] / 800
        cv2.putText(out, label, (int(x), int(y) - 8), cv2.FONT_HERSHEY_SIMPLEX, size, colour,
                    max(2, image.shape[0] // 400))  # fmt: skip
    height = round(out.shape[0] * STILL_WIDTH / out.shape[1])
    return cv2.resize(out, (STILL_WIDTH, height), interpolation=cv2.INTER_AREA)


def replay_vision(log: fl.FlightLog, still: Path | None = None) -> dict[str, Any]:
    """The vision again on the recorded frames, its sightings against the recorded ones; with
    ``still``, the lossless frame showing the most cars drawn there (:func:`draw_still`)."""
    recorded = {e.message["t_capture_ns"]: e.message for e in log.entries if e.call == "see"}
    kinds = ("lossless", "lossy")
    counts = {kind: dict.fromkeys(("frames", "sightings", "same_cell", "missing", "extra",
                                   "uncertain_flips"), 0) for kind in kinds}  # fmt: skip
    offsets: dict[str, list[float]] = {kind: [] for kind in kinds}
    turns: dict[str, list[float]] = {kind: [] for kind in kinds}
    wrong: list[dict[str, Any]] = []
    best = 0  # cars in the still drawn so far
    with tempfile.TemporaryDirectory(prefix="udan-replay-") as folder:
        vision = vision_settings(log, Path(folder)).build()
        index = 0
        for t_ns, lossless, image in fl.recorded_frames(log.path):
            scene, index = _settle(vision, image, t_ns, index)
            seen = recorded.get(t_ns)
            if seen is None:
                continue
            fmt = kinds[not lossless]
            if still is not None and lossless and len(seen["cars"]) > best:
                best = len(seen["cars"])
                cv2.imwrite(str(still), draw_still(image, vision, seen["cars"], scene))
            c = counts[fmt]
            c["frames"] += 1
            for old in seen["cars"]:
                new = scene.cars.get(old["marker"])
                if new is None:
                    c["missing"] += 1
                    continue
                c["sightings"] += 1
                if list(new.cell) == old["cell"]:
                    c["same_cell"] += 1
                else:
                    wrong.append({"frame": seen["frame"], "marker": old["marker"],
                                  "recorded": old["cell"], "replayed": list(new.cell)})  # fmt: skip
                c["uncertain_flips"] += bool(new.uncertain) != old["uncertain"]
                offsets[fmt].append(1000 * math.dist(new.xy, old["xy"]))
                turn = (new.heading - old["heading"] + math.pi) % (2 * math.pi) - math.pi
                turns[fmt].append(abs(math.degrees(turn)))
            c["extra"] += len(scene.cars.keys() - {old["marker"] for old in seen["cars"]})
    out: dict[str, Any] = {}
    for fmt, c in counts.items():
        share = round(c["same_cell"] / c["sightings"], 6) if c["sightings"] else None
        out[fmt] = {
            **c,
            "same_cell_share": share,
            "offset_mm": _spread(offsets[fmt]),
            "turn_deg": _spread(turns[fmt]),
        }
    out["cells_differing"] = wrong
    return out
