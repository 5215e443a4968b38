"""Both protocol implementations against docs/protocol_vectors.json (the spec's shared truth)."""

from __future__ import annotations

import dataclasses
import enum
import json
from pathlib import Path

import can
import pytest

from udan.edge import protocol as ep
from udan.firmware_mock import can_car, serial_link, wire
from udan.firmware_mock.core import CarCore, Telemetry

VECTORS = json.loads((Path(__file__).parents[1] / "docs" / "protocol_vectors.json").read_text())
KEYS = {int(k): bytes.fromhex(v) for k, v in VECTORS["keys"].items()}


def _event_dict(event: ep.Event) -> dict[str, object]:
    out: dict[str, object] = {"kind": type(event).__name__}
    for f in dataclasses.fields(event):
        value = getattr(event, f.name)
        out[f.name] = int(value) if isinstance(value, enum.Enum) else value
    return out


@pytest.mark.parametrize("vec", VECTORS["frames"], ids=lambda v: v["name"])
def test_both_parsers_agree_with_frame_vectors(vec: dict) -> None:
    data = bytes.fromhex(vec["hex"])
    if vec["valid"]:
        assert wire.parse(data).describe() == vec["decoded"]
        assert ep.decode(data).as_vector() == vec["decoded"]
    else:
        with pytest.raises(wire.Malformed) as fw_err:
            wire.parse(data)
        with pytest.raises(ep.FrameError) as edge_err:
            ep.decode(data)
        assert fw_err.value.reason == edge_err.value.reason == vec["reason"]


def test_valid_frame_vectors_reencode_identically_on_both_sides() -> None:
    for vec in (v for v in VECTORS["frames"] if v["valid"]):
        d = vec["decoded"]
        kind = next(k for k, n in wire.TYPE_NAMES.items() if n == d["type"])
        key = KEYS[d["car_id"]]
        args = (d["car_id"], d["session"], d["seq"], d["timestamp_us"], key)
        assert wire.encode(kind, *args, **d["payload"]).hex() == vec["hex"]
        assert ep.encode(ep.MsgType(kind), *args, d["payload"]).hex() == vec["hex"]


def test_car_core_replays_the_conversation() -> None:
    spec = VECTORS["car"]
    core = CarCore(
        spec["car_id"],
        KEYS[spec["car_id"]],
        spec["marker"],
        watchdog_us=spec["watchdog_us"],
        max_validity_us=spec["max_validity_us"],
    )
    for step in spec["steps"]:
        op, now = step["op"], step["now_us"]
        if op == "boot":
            assert core.boot(step["session"], now).hex() == step["send"]
        elif op == "receive":
            out = core.handle(bytes.fromhex(step["frame"]), now)
            assert out.verdict == step["verdict"], step["note"]
            assert [r.hex() for r in out.replies] == step["replies"], step["note"]
            assert (list(out.motor) if out.motor else None) == step["motor"], step["note"]
            assert out.halt == step["halt"], step["note"]
        elif op == "poll":
            assert core.poll(now) == step["tripped"]
        else:
            assert core.status(now, Telemetry(**step["telemetry"])).hex() == step["send"]


def test_edge_core_replays_the_conversation() -> None:
    spec = VECTORS["edge"]
    clock = {"ns": 0}
    edge = ep.EdgeProtocol(
        {c: KEYS[c] for c in spec["cars"]}, clock=lambda: clock["ns"], drift_ppm=spec["drift_ppm"]
    )
    for step in spec["steps"]:
        clock["ns"] = step["edge_ns"]
        op = step["op"]
        if op == "receive":
            event = edge.receive(bytes.fromhex(step["frame"]))
            assert _event_dict(event) == step["event"], step["note"]
        elif op == "time_request":
            assert edge.encode_time_request(step["car_id"]).hex() == step["send"]
        elif op == "command":
            frame = edge.encode_command(step["car_id"], step["action"], step["validity_ns"])
            assert frame.hex() == step["send"]
        else:
            frame = edge.encode_estop(step["car_id"], step["engage"], step["validity_ns"])
            assert frame.hex() == step["send"]


def test_reboot_vector_is_detected_by_the_edge() -> None:
    joins = [s for s in VECTORS["edge"]["steps"] if s.get("event", {}).get("kind") == "Joined"]
    assert [j["event"]["previous_session"] is not None for j in joins] == [False, True]


def test_crc16_check_value() -> None:
    spec = VECTORS["crc16"]
    assert spec["algorithm"] == "CRC-16/CCITT-FALSE"
    assert serial_link.crc16(spec["input_ascii"].encode()) == int(spec["check"], 16) == 0x29B1


@pytest.mark.parametrize("vec", VECTORS["cobs"], ids=lambda v: v["raw"][:16] or "empty")
def test_cobs_vectors(vec: dict) -> None:
    raw, encoded = bytes.fromhex(vec["raw"]), bytes.fromhex(vec["encoded"])
    assert serial_link.cobs_encode(raw) == encoded
    assert serial_link.cobs_decode(encoded) == raw


@pytest.mark.parametrize("vec", VECTORS["serial"], ids=lambda v: v["name"])
def test_serial_line_vectors(vec: dict) -> None:
    body, line = bytes.fromhex(vec["body"]), bytes.fromhex(vec["line"])
    assert serial_link.frame(body) == line
    assert serial_link.Deframer().feed(line) == [body]


@pytest.mark.parametrize("vec", VECTORS["can"], ids=lambda v: v["name"])
def test_can_vectors(vec: dict) -> None:
    frame, data = bytes.fromhex(vec["frame"]), bytes.fromhex(vec["data"])
    assert ep.can_pack(frame) == (vec["can_id"], data)
    assert ep.can_unpack(vec["can_id"], data) == frame
    car_id = int.from_bytes(frame[4:6], "big")
    if frame[1] & 0x80:
        msg = can_car.message_for(frame, car_id)
        assert (msg.arbitration_id, bytes(msg.data)) == (vec["can_id"], data)
    else:
        msg = can.Message(arbitration_id=vec["can_id"], is_extended_id=False, is_fd=True, data=data)
        assert can_car.frame_from(msg, car_id) == frame
