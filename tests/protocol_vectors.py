"""Builds docs/protocol_vectors.json (protocol v2) by running one scripted conversation.

The edge's core (``udan.edge.protocol``) and the car's core (``udan.firmware_mock.core``) talk to
each other with fixed clocks, fixed keys and fixed nonces (real ones come from ``secrets``); every
frame, verdict and event is recorded. ``tests/test_protocol_vectors.py`` checks that this script
still produces the committed file byte for byte, replays each side's half on its own core, and
checks the spec's worked examples against it. Regenerate after a deliberate wire change with

    .venv/bin/python tests/protocol_vectors.py
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from udan.edge import protocol as ep
from udan.firmware_mock import serial_link, wire
from udan.firmware_mock.core import CarCore, Outcome, Telemetry

PATH = Path(__file__).parents[1] / "docs" / "protocol_vectors.json"
KEYS = {1: bytes(range(32)), 2: bytes(range(32, 64)), 9: bytes(range(64, 96))}
MARKER = 42
# The first command's guidance: cell (3, 4)'s centre as the target (a cell is 2.8/9 m), the car
# seen 12 mm off it and 2 degrees turned, in a frame taken 18.5 ms before the command.
GUIDED = {
    "target": [1.4, 1.089, 0.0],
    "pose": [1.412, 1.085, 0.0349],
    "captured_ns": 1_001_000_000 - 18_500_000,
}
# A car entering a cell its occupant leaves sideways: it starts half a cell time later.
DELAYED = {"target": [1.4, 1.711, 0.0], "delay": 0.5}
# A protocol v1 JOIN of car 1 (session 0x1234ABCD), as a v1 car sends it.
V1_JOIN = bytes.fromhex("0183030000011234abcd00000001002a00010000000003e85668708df1c8")


def nonce(label: str) -> bytes:
    """A fixed, random-looking 16-byte nonce for the vectors (real ones come from secrets)."""
    return hashlib.sha256(label.encode()).digest()[:16]


def _nonces(prefix: str) -> Iterator[bytes]:
    n = 0
    while True:
        n += 1
        yield nonce(f"{prefix} {n}")


def event_dict(event: ep.Event) -> dict[str, Any]:
    """An edge event as the vectors write it: its kind and every field."""
    out: dict[str, Any] = {"kind": type(event).__name__}
    for f in dataclasses.fields(event):
        value = getattr(event, f.name)
        if dataclasses.is_dataclass(value):
            value = event_dict(value)  # type: ignore[arg-type]
        out[f.name] = int(value) if isinstance(value, enum.Enum) else value
    return out


def _hexes(frames: Any) -> list[str]:
    return [f.hex() for f in frames]


def guidance_dict(guidance: wire.Guidance | None) -> dict[str, Any] | None:
    """A command's target, pose and start delay as the car read them (vector form)."""
    if guidance is None:
        return None
    fields = dataclasses.asdict(guidance).items()
    return {k: list(v) if isinstance(v, tuple) else v for k, v in fields}


def edge_guidance(spec: dict[str, Any] | None) -> ep.Guidance | None:
    """The edge's guidance for a command step of the vectors (lists for the poses)."""
    if spec is None:
        return None
    pose = spec.get("pose")
    return ep.Guidance(
        tuple(spec["target"]),
        None if pose is None else tuple(pose),
        spec.get("captured_ns", 0),
        spec.get("delay", 0.0),
    )


class Script:
    """Both cores, one clock each, and the two halves of the recorded conversation."""

    def __init__(self) -> None:
        self.edge_ns = 0
        car_nonces, edge_nonces = _nonces("car"), _nonces("edge")
        self.car_nonces: list[bytes] = []
        self.edge_nonces: list[bytes] = []

        def draw(source: Iterator[bytes], used: list[bytes]) -> bytes:
            used.append(next(source))
            return used[-1]

        self.edge = ep.EdgeProtocol(
            {1: KEYS[1], 2: KEYS[2]},
            clock=lambda: self.edge_ns,
            nonce=lambda: draw(edge_nonces, self.edge_nonces),
        )
        self.car = CarCore(1, KEYS[1], MARKER, nonce=lambda: draw(car_nonces, self.car_nonces))
        self.car_steps: list[dict[str, Any]] = []
        self.edge_steps: list[dict[str, Any]] = []

    # --- the car's half ---
    def boot(self, now_us: int) -> bytes:
        join = self.car.boot(now_us)
        self.car_steps.append({"op": "boot", "now_us": now_us, "send": join.hex()})
        return join

    def to_car(self, note: str, frame: bytes, now_us: int) -> Outcome:
        out = self.car.handle(frame, now_us)
        self.car_steps.append(
            {
                "op": "receive",
                "note": note,
                "frame": frame.hex(),
                "now_us": now_us,
                "verdict": out.verdict,
                "replies": _hexes(out.replies),
                "motor": list(out.motor) if out.motor else None,
                "guidance": guidance_dict(out.guidance),
                "halt": out.halt,
            }
        )
        return out

    def status(self, now_us: int, telemetry: Telemetry) -> bytes:
        frame = self.car.status(now_us, telemetry)
        assert frame is not None
        self.car_steps.append(
            {
                "op": "status",
                "now_us": now_us,
                "telemetry": dataclasses.asdict(telemetry),
                "send": frame.hex(),
            }
        )
        return frame

    def poll(self, now_us: int) -> None:
        self.car_steps.append({"op": "poll", "now_us": now_us, "tripped": self.car.poll(now_us)})

    # --- the edge's half ---
    def to_edge(self, note: str, frame: bytes, edge_ns: int) -> tuple[ep.Event, list[bytes]]:
        self.edge_ns = edge_ns
        event = self.edge.receive(frame)
        sent = [f for _, f in self.edge.datagrams_to_send()]
        self.edge_steps.append(
            {
                "op": "receive",
                "note": note,
                "edge_ns": edge_ns,
                "frame": frame.hex(),
                "event": event_dict(event),
                "send": _hexes(sent),
            }
        )
        return event, sent

    def edge_sends(self, op: str, edge_ns: int, car_id: int, **args: Any) -> bytes:
        self.edge_ns = edge_ns
        if op == "time_request":
            frame = self.edge.encode_time_request(car_id)
        elif op == "command":
            guide = args.get("guidance")
            frame = self.edge.encode_command(
                car_id, args["action"], args["validity_ns"], edge_guidance(guide)
            )
        else:
            frame = self.edge.encode_estop(car_id, args["engage"], args["validity_ns"])
        self.edge_steps.append(
            {"op": op, "edge_ns": edge_ns, "car_id": car_id, **args, "send": frame.hex()}
        )
        return frame

    def check_session(self, car_id: int) -> int:
        session = self.edge.session(car_id)
        self.edge_steps.append({"op": "session", "car_id": car_id, "session": session})
        return session


def _tamper(frame: bytes, at: int, xor: int) -> bytes:
    out = bytearray(frame)
    out[at] ^= xor
    return bytes(out)


def conversation() -> Script:
    """The scripted conversation: join, sync, commands, faults, renewal, reboot, replays."""
    s = Script()
    car1 = 1
    join = s.boot(1_000)
    _, hello = s.to_edge(
        "a STATUS of a session this edge never opened: not_joined, answered with HELLO",
        ep.encode(
            ep.MsgType.STATUS, car1, 0x0BADCAFE, 7, 900, bytes(32),
            {"row": 0, "col": 0, "battery_mv": 1, "faults": 0, "state": 0, "done_seq": 0},
        ),
        999_000_000,
    )  # fmt: skip
    s.to_car("HELLO while the boot JOIN waits: answered with the same nonce", hello[0], 1_050)
    _, accepts = s.to_edge("JOIN of a new car: an offer (ACCEPT)", join, 1_000_100_000)
    stale = ep.encode(
        ep.MsgType.ACCEPT, car1, 0, 0, 1_000, KEYS[1],
        {"car_nonce": nonce("somebody else"), "edge_nonce": nonce("x"), "version": 2},
    )  # fmt: skip
    s.to_car("an ACCEPT for another nonce: stale_accept, nothing changes", stale, 1_080)
    s.to_car("the ACCEPT for our nonce: the session is open", accepts[0], 1_100)
    confirm = s.status(1_150, Telemetry(row=4, col=4))
    s.to_edge("the car's first frame in the offered session confirms it", confirm, 1_000_150_000)
    old_session = s.check_session(car1)

    req = s.edge_sends("time_request", 1_000_200_000, car1)
    out = s.to_car("time request", req, 1_300)
    s.to_edge("time response: rtt 200.001 us, offset rounded down", out.replies[0], 1_000_400_001)
    cmd = s.edge_sends(
        "command", 1_001_000_000, car1, action=0, validity_ns=10_000_000, guidance=GUIDED
    )
    first_ack = s.to_car("command up with its target and the measured pose, in time", cmd, 2_100)
    first_ack = first_ack.replies[0]
    dup_ack = s.to_car("the same frame again: duplicate, acked, not executed", cmd, 2_150).replies[
        0
    ]
    s.to_edge("ack accepted", first_ack, 1_001_200_000)
    s.to_edge("ack duplicate", dup_ack, 1_001_250_000)
    s.to_edge("the same ack again: replay", first_ack, 1_001_300_000)
    s.to_car("tag bit flipped: bad_tag, no reply", _tamper(cmd, -1, 1), 2_200)
    s.to_car("action changed, tag kept: bad_tag", _tamper(cmd, 14, 3), 2_210)
    forged = bytearray(cmd)
    forged[-6:] = ep.compute_tag(KEYS[2], bytes(cmd[:-6]))
    s.to_car("signed with another car's key: bad_tag", bytes(forged), 2_220)
    s.to_car("frame for car 9 sent to car 1: unknown_car", _tamper(cmd, 5, 1 ^ 9), 2_230)
    s.to_car("a protocol v1 frame: wrong_version", b"\x01" + cmd[1:], 2_240)
    s.to_car("truncated by one byte: malformed", cmd[:-1], 2_250)
    s.to_car("one byte too many: malformed", cmd + b"\x00", 2_260)
    session_key = ep.derive_session(KEYS[1], nonce("car 1"), nonce("edge 1"))[1]
    turned = ep.encode(
        ep.MsgType.COMMAND, car1, s.edge.session(car1), 900, 2_265, session_key,
        {"action": 0, "deadline_us": 12_000, "guide": 3, "target_x_mm": 1400,
         "target_y_mm": 1089, "pose_x_mm": 1412, "pose_y_mm": 1085, "pose_heading_mrad": 4000,
         "pose_age_us": 18_500},
    )  # fmt: skip
    s.to_car("signed, but the pose heading is beyond pi: malformed, not executed", turned, 2_265)
    s.to_car("a car->edge frame sent to the car: malformed", first_ack, 2_270)
    s.to_car("a session the car does not hold: wrong_session, no reply", _tamper(cmd, 9, 1), 2_280)
    deadline_cmd = s.edge_sends(
        "command", 1_001_567_891, car1, action=4, validity_ns=10_000_000
    )  # deadline rounding: see spec section 7
    s.to_car("wait, deadline rounded down", deadline_cmd, 2_700)
    c3 = s.edge_sends("command", 1_002_000_000, car1, action=3, validity_ns=10_000_000)
    c4 = s.edge_sends("command", 1_002_100_000, car1, action=1, validity_ns=10_000_000)
    ack4 = s.to_car("the newer command arrives first", c4, 3_200).replies[0]
    ack3 = s.to_car("the older one after it: replay, acked, not executed", c3, 3_300).replies[0]
    s.to_edge("ack replay arrives before the ack of the newer (reordered)", ack3, 1_002_400_000)
    s.to_edge("ack of the newer still taken: unseen seq inside the window", ack4, 1_002_450_000)
    late = s.edge_sends("command", 1_003_000_000, car1, action=2, validity_ns=10_000_000)
    s.to_car("arrives after its deadline: expired", late, 14_200)
    far = s.edge_sends("command", 1_015_000_000, car1, action=2, validity_ns=2_000_000_000)
    s.to_car("deadline 2 s ahead (more than 1 s): bad_time", far, 16_100)
    engage = s.edge_sends("estop", 1_017_000_000, car1, engage=True, validity_ns=10_000_000)
    s.to_car("estop engage after its deadline: accepted, motors halt, latched", engage, 40_000)
    up = s.edge_sends("command", 1_030_000_000, car1, action=0, validity_ns=10_000_000)
    s.to_car("command while latched: estopped", up, 30_100)
    stop = s.edge_sends("command", 1_030_100_000, car1, action=5, validity_ns=10_000_000)
    s.to_car("stop is allowed while latched", stop, 30_200)
    release = s.edge_sends("estop", 1_030_200_000, car1, engage=False, validity_ns=10_000_000)
    s.to_car("estop release, in time", release, 30_300)
    down = s.edge_sends(
        "command", 1_031_000_000, car1, action=1, validity_ns=10_000_000, guidance=DELAYED
    )
    s.to_car("command down after release, to start half a cell time later", down, 31_100)
    for i in range(9):
        s.to_car(
            f"replay {i + 1} of 9 at one instant: 8 answered, then the rate limit", down, 200_000
        )
    s.poll(431_099)  # the watchdog counts from the move's start: 31 100 + 100 000 us
    s.poll(431_100)
    watchdog = s.status(432_000, Telemetry(row=5, col=4, battery_mv=8196, done_seq=11))
    s.to_edge("status with the watchdog flag", watchdog, 1_331_000_000)
    s.to_edge("status with a flipped tag bit: bad_tag", _tamper(watchdog, -1, 1), 1_331_100_000)
    s.to_edge("a protocol v1 JOIN: wrong_version, one line to log", V1_JOIN, 1_331_200_000)
    v3 = ep.encode(
        ep.MsgType.JOIN, car1, 0, 0, 332_100, KEYS[1],
        {"marker": MARKER, "cause": 0, "min_version": 3, "max_version": 4,
         "car_nonce": nonce("a later car")},
    )  # fmt: skip
    s.to_edge("a JOIN offering v3-v4 only: wrong_version", v3, 1_331_300_000)
    s.to_edge("truncated: malformed", watchdog[:-2], 1_331_400_000)
    s.to_edge("an edge->car frame sent to the edge: malformed", down, 1_331_500_000)
    s.to_edge("car 7 has no key: unknown_car", _tamper(watchdog, 5, 1 ^ 7), 1_331_600_000)
    old_key = ep.derive_session(KEYS[1], nonce("car 1"), nonce("edge 1"))[1]
    unsolicited = ep.encode(
        ep.MsgType.TIME_RESPONSE, car1, old_session, 1_000, 332_200, old_key,
        {"t1_ns": 5, "t2_us": 332_200, "t3_us": 332_200},
    )  # fmt: skip
    s.to_edge("time response to no request: unsolicited", unsolicited, 1_331_700_000)
    s.to_edge("the first JOIN replayed: an offer nobody takes", join, 1_331_800_000)
    s.check_session(car1)

    # a HELLO to a live car: it asks for a new session, keeps the old one until the edge moves
    _, renew_hello = s.to_edge(
        "a STATUS of an unknown session once the car is silent: HELLO",
        ep.encode(
            ep.MsgType.STATUS, car1, 0x0BADCAFE, 8, 900, bytes(32),
            {"row": 0, "col": 0, "battery_mv": 1, "faults": 0, "state": 0, "done_seq": 0},
        ),
        1_900_000_000,
    )  # fmt: skip
    out = s.to_car(
        "HELLO to a car in a session: JOIN (cause hello), session kept", renew_hello[0], 800_000
    )
    _, offer = s.to_edge("the JOIN the HELLO asked for: an offer", out.replies[0], 1_900_100_000)
    s.to_car("ACCEPT: the new session is current, the old one kept meanwhile", offer[0], 800_100)
    confirm = s.status(800_150, Telemetry(row=5, col=4, battery_mv=8196))
    s.to_edge("confirmed: the new session is current, the old one kept 1 s", confirm, 1_900_150_000)

    def in_old(seq: int, now_us: int) -> bytes:
        return ep.encode(
            ep.MsgType.TIME_REQUEST, car1, old_session, seq, now_us, old_key, {"t1_ns": seq}
        )

    s.to_car(
        "a frame of the old session before the edge moved: still taken",
        in_old(40, 800_200),
        800_200,
    )
    req = s.edge_sends("time_request", 1_900_300_000, car1)
    s.to_car("the edge's first frame in the new session: the old one is dropped", req, 800_300)
    s.to_car("the old session after that: wrong_session", in_old(41, 800_400), 800_400)

    # reboot: the latch and every session are gone; the edge sees a boot JOIN
    s.to_car(
        "estop engage",
        s.edge_sends("estop", 1_901_000_000, car1, engage=True, validity_ns=10_000_000),
        801_000,
    )
    rejoin = s.boot(500)
    _, offer = s.to_edge("JOIN after a reboot: an offer", rejoin, 2_000_000_000)
    s.to_car("ACCEPT after the reboot", offer[0], 700)
    confirm = s.status(750, Telemetry(row=5, col=4, battery_mv=8196))
    s.to_edge("confirmed: a reboot (the clock sync is void)", confirm, 2_000_050_000)
    s.to_car("a frame of the session before the reboot: wrong_session", req, 800)
    s.edge_sends("time_request", 2_000_100_000, car1)
    leave = s.car.leave(900, 1)
    assert leave is not None
    s.car_steps.append({"op": "leave", "now_us": 900, "reason": 1, "send": leave.hex()})
    s.to_edge("LEAVE (low battery): the session ends", leave, 2_000_200_000)

    # car 2: one recorded JOIN replayed 9 times at one instant: 8 offers, then the rate limit
    car2 = CarCore(2, KEYS[2], 7, nonce=lambda: nonce("car two"))
    join2 = car2.boot(10)
    for i in range(9):
        s.to_edge(f"JOIN of car 2, copy {i + 1} of 9 at one instant", join2, 2_100_000_000)
    return s


def frame_vectors(s: Script) -> list[dict[str, Any]]:
    """Single frames: every type as the conversation sent it, and broken ones with the reason."""
    by_type: dict[int, bytes] = {}
    taken = ("accepted", "joined", "hello", "duplicate")
    for step in s.edge_steps + s.car_steps:
        genuine = [*step.get("replies", [])]
        genuine += [step["send"]] if isinstance(step.get("send"), str) else step.get("send", [])
        if step.get("verdict") in taken or step.get("event", {}).get("kind") not in (
            None,
            "Rejected",
        ):
            genuine.append(step["frame"])
        for h in genuine:
            data = bytes.fromhex(h)
            by_type.setdefault(ep.decode(data).type, data)
    out = []
    for kind in ep.MsgType:
        data = by_type[kind]
        out.append({"name": kind.name.lower(), "hex": data.hex(), "valid": True,
                    "decoded": ep.decode(data).as_vector()})  # fmt: skip
    cmd, join = by_type[ep.MsgType.COMMAND], by_type[ep.MsgType.JOIN]
    broken = {
        "empty": b"",
        "protocol v1": V1_JOIN,
        "truncated header": cmd[:10],
        "truncated by one byte": cmd[:-1],
        "one byte too many": cmd + b"\x00",
        "unknown type": cmd[:1] + b"\x07" + cmd[2:],
        "payload length field wrong": cmd[:2] + b"\x08" + cmd[3:],
        "reserved flags set": cmd[:3] + b"\x01" + cmd[4:],
        "link id of the other direction": cmd[:41] + b"\x01" + cmd[42:],
        "unknown action 6": cmd[:14] + b"\x06" + cmd[15:],
        "unknown guide flag 4": cmd[:23] + b"\x07" + cmd[24:],
        "target fields without the target flag": cmd[:23] + b"\x02" + cmd[24:],
        "pose heading beyond pi": cmd[:34] + (3143).to_bytes(2, "big") + cmd[36:],
        "target heading beyond -pi": cmd[:28] + (-3143).to_bytes(2, "big", signed=True) + cmd[30:],
        "pose older than a second": cmd[:36] + (1_000_001).to_bytes(4, "big") + cmd[40:],
        "start delay beyond two cell times": cmd[:40] + bytes([201]) + cmd[41:],
        "car id 0": cmd[:4] + b"\x00\x00" + cmd[6:],
        "session 0 on a command": cmd[:6] + bytes(4) + cmd[10:],
        "seq 0 on a command": cmd[:10] + bytes(4) + cmd[14:],
        "session on a JOIN": join[:9] + b"\x01" + join[10:],
        "seq on a JOIN": join[:13] + b"\x01" + join[14:],
        "JOIN version range upside down": join[: 9 + 8] + b"\x03\x02" + join[19:],
    }
    for name, data in broken.items():
        try:
            ep.decode(data)
        except ep.FrameError as err:
            out.append({"name": name, "hex": data.hex(), "valid": False, "reason": err.reason})
        else:
            raise AssertionError(f"vector {name!r} decodes")
    return out


def cobs_vectors() -> list[dict[str, str]]:
    """COBS cases, the block rule among them (spec section 9)."""
    run = bytes(range(1, 255))  # 254 non-zero bytes: one full block
    raws = [b"", b"\x00", b"\x00\x00", b"\x11\x22\x00\x33", b"\x11\x22\x33\x44",
            b"\x11\x00\x00\x00", run[:253], run, run + b"\x00", run + b"\x01",
            b"\x00" + run, run + run[:1]]  # fmt: skip
    return [{"raw": r.hex(), "encoded": serial_link.cobs_encode(r).hex()} for r in raws]


def build() -> dict[str, Any]:
    """Everything in docs/protocol_vectors.json, from the implementation."""
    s = conversation()
    frames = frame_vectors(s)
    valid = {f["name"]: bytes.fromhex(f["hex"]) for f in frames if f["valid"]}
    valid_command = valid["command"]
    car_nonce, edge_nonce = nonce("car 1"), nonce("edge 1")
    session_id, session_key = ep.derive_session(KEYS[1], car_nonce, edge_nonce)
    internal = [
        ("move up seq 2", serial_link.encode_message(serial_link.MOVE, seq=2, action=0)),
        (
            "move up seq 3, guided",
            serial_link.encode_message(
                serial_link.MOVE,
                seq=3,
                action=0,
                **wire.guide_payload(wire.guidance(ep.decode(valid_command).fields)),
            ),
        ),
        ("stop (watchdog)", serial_link.encode_message(serial_link.STOP, reason=1)),
        (
            "state",
            serial_link.encode_message(
                serial_link.STATE, row=3, col=4, battery_mv=8198, flags=0, done_seq=2
            ),
        ),
    ]
    return {
        "comment": "Test vectors for docs/protocol.md (protocol version 2), made by "
        "tests/protocol_vectors.py. Keys, clocks and nonces are fixed; car steps and edge "
        "steps replay one conversation, each side's state carried from step to step.",
        "protocol_version": ep.PROTOCOL_VERSION,
        "keys": {str(c): k.hex() for c, k in KEYS.items()},
        "session": {
            "car_id": 1,
            "car_nonce": car_nonce.hex(),
            "edge_nonce": edge_nonce.hex(),
            "session_id": session_id,
            "session_key": session_key.hex(),
        },
        "crc16": {
            "algorithm": "CRC-16/CCITT-FALSE",
            "poly": "0x1021",
            "init": "0xffff",
            "refin": False,
            "refout": False,
            "xorout": "0x0000",
            "input_ascii": "123456789",
            "check": f"0x{serial_link.crc16(b'123456789'):04x}",
        },
        "cobs": cobs_vectors(),
        "cobs_decode_only": [
            {"encoded": "ff" + bytes(range(1, 255)).hex() + "01", "raw": bytes(range(1, 255)).hex()}
        ],
        "serial": [
            {"name": name, "body": body.hex(), "line": serial_link.frame(body).hex()}
            for name, body in [
                *internal,
                ("a protocol frame (wired serial link)", valid["command"]),
            ]
        ],
        "frames": frames,
        "car": {
            "car_id": 1,
            "marker": MARKER,
            "watchdog_us": s.car.watchdog_us,
            "max_validity_us": s.car.max_validity_us,
            "cell_time_us": s.car.cell_time_us,
            "nonces": _hexes(s.car_nonces),
            "steps": s.car_steps,
        },
        "edge": {
            "cars": [1, 2],
            "drift_ppm": ep.DRIFT_PPM,
            "nonces": _hexes(s.edge_nonces),
            "steps": s.edge_steps,
        },
        "can": [
            {
                "name": f"{name} (car 1)",
                "frame": valid[name].hex(),
                "can_id": ep.can_pack(valid[name])[0],
                "data": ep.can_pack(valid[name])[1].hex(),
            }
            for name in ("command", "estop", "ack", "accept", "join", "time_response")
        ],
    }


def main() -> None:
    """Write docs/protocol_vectors.json."""
    PATH.write_text(json.dumps(build(), indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
