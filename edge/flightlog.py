"""The flight recording's format (MCAP): its channels, their schemas, and reading one back.

A recording (``udan-edge --record run.mcap``, written by :mod:`udan.edge.recorder`) is an MCAP
file (the format rosbag2 writes by default; Foxglove opens it) whose log times are this host's
monotonic clock in nanoseconds (the clock every span of the edge is measured on; the run's
metadata holds one reading of it beside the realtime clock, to turn it into wall time):

- ``/camera/lossless`` (``foxglove.RawImage``, mono8, protobuf, uncompressed): every frame a
  decision used; ``/camera/jpeg``
  (``foxglove.CompressedImage``): the others, at the rate and quality asked (lossless ones go to
  the first topic); both stamped at capture, their sequence number the frame's.
- ``/vision/scene``: each frame's scene as the core took it: the car sightings (cell, metres,
  heading, offset, error budget, uncertain), the static cells, the link's ready cars, ``now``.
- ``/core/due``: each step check: ``now`` and the cars the link said were still moving.
- ``/core/fleet_state``, ``/core/decision``: each decision's fleet state (slots, fresh cars,
  cells, static cells, held cells, moving and uncertain cars) and the decision (``now``, the
  decision clock, the policy's actions, the commands after the safety filter, rewards, spans,
  each command's guidance: target pose and start delay, and the car whose ACK it waits for).
- ``/link/dispatch``: each command's sends and ack (first send, attempts, ack time, the car's
  receive time, result).
- ``/core/recentred``: each re-centring round (the cars off their cells' centres, each car's
  command and target) with its dispatch, as on ``/link/dispatch``.
- ``/core/control``: the core's other calls (``start``, ``guard`` with the cars still moving,
  ``wait_for_moves``, ``new_episode``, ``credit_last_step``, ``emergency_stop``).
- ``/edge/step``, ``/edge/recentre``, ``/edge/frame``, ``/edge/event``: the telemetry records
  (each step's and re-centring round's spans and counts, each frame's age and frame-to-state
  span; joins, leaves, stalls, guard stops, camera news).

The JSON channels carry a JSON Schema each. Messages of the core's journal (every topic above
but the camera's and the telemetry's) carry ``seq``, the order the core consumed them in (also
their MCAP sequence number): :func:`journal` reads them back as the core's inputs, which
:mod:`udan.edge.replay` feeds to a new core. The run's metadata (MCAP metadata ``udan-edge``):
the code version, the model file and its SHA-256, the task, the calibration file and its
SHA-256 (the file itself is an attachment), the camera URL and its granted mode, the fleet's car
ids, markers and addresses (never a key), the vision settings and the step timing.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # the recorder process writes them; only a replay builds them again
    from udan.edge.core import Recentring, StepTiming
    from udan.edge.decide import Decision
    from udan.edge.fleet import FleetState
    from udan.edge.link import DispatchReport
    from udan.edge.protocol import Guidance
    from udan.edge.vision import Scene

PROFILE = "udan-edge"
"""The MCAP header's profile of a flight recording."""
META = "udan-edge"
"""Name of the run's MCAP metadata record."""
META_KEYS = ("model", "model_sha256", "task", "fleet", "vision", "lost_s", "motion")
"""What a replay reads of the metadata."""
CALIBRATION_ATTACHMENT = "calibration.yaml"
LOSSLESS_TOPIC = "/camera/lossless"
JPEG_TOPIC = "/camera/jpeg"
IMAGE_TOPICS = (LOSSLESS_TOPIC, JPEG_TOPIC)
SCENE_TOPIC = "/vision/scene"
DUE_TOPIC = "/core/due"
STATE_TOPIC = "/core/fleet_state"
DECISION_TOPIC = "/core/decision"
DISPATCH_TOPIC = "/link/dispatch"
RECENTRED_TOPIC = "/core/recentred"
CONTROL_TOPIC = "/core/control"
TELEMETRY_TOPICS = {"step": "/edge/step", "recentre": "/edge/recentre", "frame": "/edge/frame"}
EVENT_TOPIC = "/edge/event"
JOURNAL_TOPICS = (
    SCENE_TOPIC, DUE_TOPIC, DECISION_TOPIC, DISPATCH_TOPIC, RECENTRED_TOPIC, CONTROL_TOPIC,
)  # fmt: skip


class FlightLogError(ValueError):
    """A file that is not a readable flight recording; one line."""


# -- schemas ----------------------------------------------------------------------------------
def _obj(properties: Mapping[str, Any], required: tuple[str, ...] = ()) -> dict[str, Any]:
    return {"type": "object", "properties": dict(properties), "required": list(required)}


def _arr(items: Mapping[str, Any]) -> dict[str, Any]:
    return {"type": "array", "items": dict(items)}


_INT = {"type": "integer"}
_NUM = {"type": "number"}
_BOOL = {"type": "boolean"}
_STR = {"type": "string"}
_CELL = {**_arr(_INT), "minItems": 2, "maxItems": 2}
_CELLS_BY_KIND = {"type": "object", "additionalProperties": _arr(_CELL)}
_SEQ = {"seq": _INT}
_SIGHTING = _obj(
    {
        "marker": _INT, "cell": _CELL, "xy": _arr(_NUM), "heading": _NUM,
        "offset": _arr(_NUM), "inside": _BOOL, "uncertain": _BOOL, "error_budget_m": _NUM,
    },
    ("marker", "cell", "xy", "heading", "offset", "inside", "uncertain", "error_budget_m"),
)  # fmt: skip
_GUIDE = _obj({"target": _arr(_NUM), "delay": _NUM}, ("target", "delay"))
_NULL_INT = {"type": ["integer", "null"]}
_DISPATCH = {
    **_SEQ, "state_ns": _INT, "decision_ns": _INT, "deadline_ns": _INT,
    "cars": _arr(_obj({
        "car_id": _INT, "action": _INT, "seq": _INT, "first_sent_ns": _NULL_INT,
        "attempts": _INT, "acked": _BOOL, "acked_ns": _NULL_INT, "car_received_ns": _NULL_INT,
        "result": _STR, "car_deadline_us": _NULL_INT, "car_rx_us": _NULL_INT,
        "slow_sends": _INT,
    }, ("car_id", "action", "acked", "result"))),
    "on_time": _INT, "retried": _INT, "missed": _INT, "not_ready": _INT,
    "slow_sends": _INT, "late_sends": _INT,
}  # fmt: skip
_DISPATCH_REQUIRED = ("seq", "state_ns", "decision_ns", "deadline_ns", "cars")
SCHEMAS: dict[str, dict[str, Any]] = {
    SCENE_TOPIC: _obj(
        {
            **_SEQ, "now_ns": _INT, "ready": _arr(_INT), "frame": _INT, "t_capture_ns": _INT,
            "t_arrival_ns": {"type": ["integer", "null"]}, "calibrated": _BOOL,
            "vision_ns": _INT, "cars": _arr(_SIGHTING), "cells": _CELLS_BY_KIND,
        },
        ("seq", "now_ns", "ready", "frame", "t_capture_ns", "calibrated", "cars", "cells"),
    ),
    DUE_TOPIC: _obj({**_SEQ, "now_ns": _INT, "moving": _arr(_INT)}, ("seq", "now_ns", "moving")),
    STATE_TOPIC: _obj(
        {
            **_SEQ, "frame": _INT, "t_capture_ns": _INT, "slots": _arr(_arr(_INT)),
            "fresh": _arr(_INT), "cells": _arr(_arr(_INT)), "static": _CELLS_BY_KIND,
            "others": _arr(_CELL), "moving": _arr(_arr(_INT)), "uncertain": _arr(_INT),
            "calibrated": _BOOL,
        },
        ("seq", "frame", "slots", "cells", "static"),
    ),
    DECISION_TOPIC: _obj(
        {
            **_SEQ, "now_ns": _INT, "decided_ns": _INT, "frame": _INT, "cars": _arr(_INT),
            "actions": _arr(_INT), "commands": _arr(_INT), "rewards": _arr(_NUM),
            "blocked": _INT, "stopped": _INT, "formed": _BOOL,
            "spans_ns": {"type": "object", "additionalProperties": _INT},
            "guidance": {"type": "object", "additionalProperties": _GUIDE},
            "after": {"type": "object", "additionalProperties": _INT},
        },
        ("seq", "now_ns", "decided_ns", "cars", "actions", "commands", "rewards"),
    ),
    DISPATCH_TOPIC: _obj(_DISPATCH, _DISPATCH_REQUIRED),
    RECENTRED_TOPIC: _obj(
        {**_DISPATCH, "frame": _INT, "cars_off": _arr(_INT),
         "commands": {"type": "object", "additionalProperties": _INT},
         "guidance": {"type": "object", "additionalProperties": _GUIDE}},
        (*_DISPATCH_REQUIRED, "frame", "cars_off", "commands", "guidance"),
    ),
    CONTROL_TOPIC: _obj(
        {
            **_SEQ,
            "call": {"enum": ["start", "guard", "wait_for_moves", "new_episode",
                              "credit_last_step", "emergency_stop"]},
            "now_ns": _INT, "moving": _arr(_INT),
            "rewards": {"type": ["array", "null"], "items": _NUM},
            "step_timeout_ns": _INT, "unseen_grace_ns": _INT,
        },
        ("seq", "call"),
    ),
    **{
        topic: _obj({"kind": _STR, "t_ns": _INT}, ("kind",))
        for topic in (*TELEMETRY_TOPICS.values(), EVENT_TOPIC)
    },
}  # fmt: skip


# -- to JSON ----------------------------------------------------------------------------------
def _cells_by_kind(cells: Mapping[str, frozenset[tuple[int, int]]]) -> dict[str, list]:
    return {kind: sorted([int(r), int(c)] for r, c in found) for kind, found in cells.items()}


def scene_json(seq: int, now: int, ready: tuple[int, ...], scene: Scene) -> dict[str, Any]:
    return {
        "seq": seq,
        "now_ns": now,
        "ready": sorted(int(c) for c in ready),
        "frame": scene.frame_index,
        "t_capture_ns": scene.t_capture_ns,
        "t_arrival_ns": scene.t_arrival_ns,
        "calibrated": scene.calibrated,
        "vision_ns": scene.vision_ns,
        "cars": [
            {
                "marker": s.marker,
                "cell": [int(s.cell[0]), int(s.cell[1])],
                "xy": [float(s.xy[0]), float(s.xy[1])],
                "heading": float(s.heading),
                "offset": [float(s.offset[0]), float(s.offset[1])],
                "inside": bool(s.inside),
                "uncertain": bool(s.uncertain),
                "error_budget_m": float(s.error_budget_m),
            }
            for s in scene.cars.values()
        ],
        "cells": _cells_by_kind(scene.cells),
    }


def state_json(seq: int, state: FleetState) -> dict[str, Any]:
    return {
        "seq": seq,
        "frame": state.frame,
        "t_capture_ns": state.t_capture_ns,
        "slots": sorted([int(c), int(s)] for c, s in state.slots.items()),
        "fresh": sorted(int(c) for c in state.fresh),
        "cells": sorted([int(c), int(r), int(k)] for c, (r, k) in state.cells.items()),
        "static": _cells_by_kind(state.static),
        "others": [[int(r), int(c)] for r, c in state.others],
        "moving": sorted([int(c), int(a)] for c, a in state.moving.items()),
        "uncertain": sorted(int(c) for c in state.uncertain),
        "calibrated": bool(state.calibrated),
    }


def decided(decision: Decision) -> dict[str, Any]:
    """What a decision decided, as recorded (a replay's decision must give the same)."""
    return {
        "cars": [int(c) for c in decision.cars],
        "actions": decision.actions.tolist(),
        "commands": decision.commands.tolist(),
        "rewards": [float(r) for r in decision.rewards],
        "blocked": decision.blocked,
        "stopped": decision.stopped,
        "formed": bool(decision.formed),
        "guidance": guidance_json(decision.guidance),
        "after": {str(c): int(leader) for c, leader in decision.after.items()},
    }


def decision_json(
    seq: int, now: int, decided_ns: int, state: FleetState, decision: Decision
) -> dict[str, Any]:
    return {
        "seq": seq,
        "now_ns": now,
        "decided_ns": decided_ns,
        "frame": state.frame,
        **decided(decision),
        "spans_ns": dict(decision.spans_ns),
    }


def guidance_json(guidance: Mapping[int, Guidance]) -> dict[str, dict[str, Any]]:
    """Each command's target pose and start delay (the measured pose is in the scene)."""
    return {
        str(c): {"target": [float(v) for v in g.target], "delay": float(g.delay)}
        for c, g in guidance.items()
    }


_COMMAND_FIELDS = (
    "car_id", "action", "seq", "first_sent_ns", "attempts", "acked", "acked_ns",
    "car_received_ns", "result", "car_deadline_us", "car_rx_us", "slow_sends",
)  # fmt: skip
_DISPATCH_COUNTS = ("on_time", "retried", "missed", "not_ready", "slow_sends", "late_sends")


def dispatch_json(seq: int, state_ns: int, report: DispatchReport) -> dict[str, Any]:
    return {
        "seq": seq,
        "state_ns": state_ns,
        "decision_ns": report.decision_ns,
        "deadline_ns": report.deadline_ns,
        "cars": [{k: getattr(r, k) for k in _COMMAND_FIELDS} for r in report.cars.values()],
        **{k: getattr(report, k) for k in _DISPATCH_COUNTS},
    }


def recentred_json(seq: int, recentring: Recentring, report: DispatchReport) -> dict[str, Any]:
    return {
        **dispatch_json(seq, report.decision_ns, report),  # decided as dispatched
        "frame": recentring.frame,
        "cars_off": [int(c) for c in recentring.cars],
        "commands": {str(c): int(a) for c, a in recentring.commands.items()},
        "guidance": guidance_json(recentring.guidance),
    }


def control_json(seq: int, call: str, inputs: tuple) -> dict[str, Any]:
    out: dict[str, Any] = {"seq": seq, "call": call}
    if call == "start":
        stepped, timing = inputs
        out.update(now_ns=stepped, step_timeout_ns=timing.step_timeout_ns,
                   unseen_grace_ns=timing.unseen_grace_ns)  # fmt: skip
    elif call in ("wait_for_moves", "new_episode"):
        out["now_ns"] = inputs[0]
    elif call == "guard":
        out["moving"] = sorted(int(c) for c in inputs[0])
    elif call == "credit_last_step":
        rewards = inputs[0]
        out["rewards"] = None if rewards is None else [float(r) for r in rewards]
    return out


# -- from JSON --------------------------------------------------------------------------------
def _kinds(cells: Mapping[str, list]) -> dict[str, frozenset[tuple[int, int]]]:
    return {kind: frozenset((r, c) for r, c in found) for kind, found in cells.items()}


def scene_of(message: Mapping[str, Any]) -> Scene:
    """The Scene a `scene_json` message was written from (equal field for field)."""
    from udan.edge.vision import CarSighting, Scene

    cars = {
        s["marker"]: CarSighting(
            marker=s["marker"],
            cell=tuple(s["cell"]),
            xy=tuple(s["xy"]),
            heading=s["heading"],
            offset=tuple(s["offset"]),
            inside=s["inside"],
            uncertain=s["uncertain"],
            error_budget_m=s["error_budget_m"],
        )
        for s in message["cars"]
    }
    return Scene(
        t_capture_ns=message["t_capture_ns"],
        frame_index=message["frame"],
        calibrated=message["calibrated"],
        cars=cars,
        cells=_kinds(message["cells"]),
        vision_ns=message["vision_ns"],
        t_arrival_ns=message["t_arrival_ns"],
    )


def report_of(message: Mapping[str, Any]) -> DispatchReport:
    """The DispatchReport a `dispatch_json` message was written from."""
    from udan.edge.link import CommandReport, DispatchReport

    cars = {r["car_id"]: CommandReport(**r) for r in message["cars"]}
    counts = {k: message[k] for k in _DISPATCH_COUNTS}
    return DispatchReport(message["decision_ns"], message["deadline_ns"], cars, **counts)


# -- reading ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Entry:
    """One input of the core's journal as recorded: the call, and its message."""

    seq: int
    call: str
    message: dict[str, Any]


@dataclass
class FlightLog:
    """A flight recording read back: its metadata, the core's journal, and what else it holds."""

    path: Path
    meta: dict[str, Any]
    entries: list[Entry]
    telemetry: list[dict[str, Any]] = field(default_factory=list)
    frames: int = 0
    """Camera frames in the recording (:func:`recorded_frames` reads them)."""
    calibration: bytes | None = None
    schemas: dict[str, tuple[str, str]] = field(default_factory=dict)
    """Topic -> (schema name, schema encoding) of every channel."""

    @property
    def timing(self) -> StepTiming:
        from udan.edge.core import StepTiming

        start = next(e.message for e in self.entries if e.call == "start")
        return StepTiming(start["step_timeout_ns"], start["unseen_grace_ns"])

    def gaps(self) -> int:
        """Journal entries missing from the recording (the recorder's queue was full)."""
        seqs = [e.seq for e in self.entries]
        return (seqs[-1] - seqs[0] + 1 - len(seqs)) if seqs else 0


_CALL_OF_TOPIC = {
    SCENE_TOPIC: "see", DUE_TOPIC: "due", DECISION_TOPIC: "decide", DISPATCH_TOPIC: "dispatched",
    RECENTRED_TOPIC: "recentred",
}  # fmt: skip


def entry_of(topic: str, body: dict[str, Any]) -> Entry | None:
    """The journal entry a message of ``topic`` is; None for the topics that are not."""
    if topic in _CALL_OF_TOPIC:
        return Entry(body["seq"], _CALL_OF_TOPIC[topic], body)
    if topic == CONTROL_TOPIC:
        return Entry(body["seq"], body["call"], body)
    return None


def _reader(stream: Any) -> Any:
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    try:
        return make_reader(stream)
    except (McapError, ValueError, EOFError) as err:
        raise FlightLogError(f"not an MCAP file ({err})") from None


def read_flight_log(path: str | Path) -> FlightLog:
    """The recording at ``path``; a one-line `FlightLogError` for a file that is not one
    (another format, an MCAP file of someone else's, a file cut short)."""
    from mcap.exceptions import McapError

    path = Path(path)
    if not path.is_file():
        raise FlightLogError(f"{path}: no such file")
    entries: list[Entry] = []
    telemetry: list[dict[str, Any]] = []
    frames = 0
    try:
        with path.open("rb") as stream:
            reader = _reader(stream)
            header = reader.get_header()
            if header.profile != PROFILE:
                raise FlightLogError(
                    f"{path} is an MCAP file but not a udan-edge recording "
                    f"(profile {header.profile!r})"
                )
            summary = reader.get_summary()
            if summary is None:
                raise FlightLogError(f"{path} is cut short: it has no summary (not closed)")
            schemas = {
                channel.topic: (summary.schemas[channel.schema_id].name,
                                summary.schemas[channel.schema_id].encoding)
                for channel in summary.channels.values()
            }  # fmt: skip
            meta_records = [m for m in reader.iter_metadata() if m.name == META]
            if not meta_records:
                raise FlightLogError(f"{path} has no udan-edge metadata")
            meta = {k: json.loads(v) for k, v in meta_records[0].metadata.items()}
            missing = [key for key in META_KEYS if key not in meta]
            if missing:
                raise FlightLogError(
                    f"{path} was written by another version: its metadata has no "
                    f"{', '.join(missing)}"
                )
            calibration = next(
                (a.data for a in reader.iter_attachments() if a.name == CALIBRATION_ATTACHMENT),
                None,
            )
            for _, channel, message in reader.iter_messages():
                topic = channel.topic
                if topic in IMAGE_TOPICS:
                    frames += 1
                    continue
                body = json.loads(message.data)
                entry = entry_of(topic, body)
                if entry is not None:
                    entries.append(entry)
                elif topic != STATE_TOPIC:
                    telemetry.append(body)
    except (McapError, EOFError, ValueError, KeyError, OSError) as err:
        if isinstance(err, FlightLogError):
            raise
        detail = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise FlightLogError(f"{path}: cannot be read as a flight recording ({detail})") from None
    entries.sort(key=lambda e: e.seq)
    if not any(e.call == "start" for e in entries):
        raise FlightLogError(f"{path} holds no journal of the control core")
    return FlightLog(path, meta, entries, telemetry, frames, calibration, schemas)


def recorded_frames(path: str | Path) -> Iterator[tuple[int, bool, np.ndarray]]:
    """(capture time, lossless or not, grayscale image) of every frame in the recording, in
    capture order."""
    import cv2
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
    from mcap.reader import make_reader

    with Path(path).open("rb") as stream:
        reader = make_reader(stream)
        for _, channel, message in reader.iter_messages(topics=list(IMAGE_TOPICS)):
            if channel.topic == LOSSLESS_TOPIC:
                raw = RawImage()
                raw.ParseFromString(message.data)
                pixels = np.frombuffer(raw.data, np.uint8).reshape(raw.height, raw.step)
                yield message.log_time, True, pixels[:, : raw.width]
            else:
                jpeg = CompressedImage()
                jpeg.ParseFromString(message.data)
                data = np.frombuffer(jpeg.data, np.uint8)
                yield message.log_time, False, cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
