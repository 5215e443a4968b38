"""fleet.toml: which cars exist, their markers, keys and addresses (format in docs/protocol.md §12).

Every problem becomes one ``FleetError`` with a one-line message naming the file and the car, so
the CLI can print it and exit 2 instead of showing a traceback.
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from firmware_mock.faults import Faults

KEY_BYTES = 32
_CAR_FIELDS = {"id", "marker", "port", "address", "key", "key_file", "serial", "start", "faults"}
_HEX = re.compile(r"[0-9a-fA-F]*")


class FleetError(ValueError):
    """A fleet file that cannot be used, with a one-line reason."""


@dataclass(frozen=True)
class CarSpec:
    """One car of the fleet as the mock firmware needs it."""

    car_id: int
    marker: int
    key: bytes = field(repr=False)
    host: str = "127.0.0.1"
    port: int = 0
    start: tuple[int, int] = (4, 4)
    faults: Mapping[str, Any] = field(default_factory=dict)


def _int(value: Any, what: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise FleetError(f"{what} must be an integer in {lo}-{hi}, got {value!r}")
    return value


def _key_from_text(text: str, what: str) -> bytes:
    text = text.strip()
    if not _HEX.fullmatch(text) or len(text) % 2:
        raise FleetError(f"{what} is not hex")
    key = bytes.fromhex(text)
    if len(key) != KEY_BYTES:
        raise FleetError(
            f"{what} must be {KEY_BYTES} bytes ({2 * KEY_BYTES} hex digits), got {len(key)} bytes"
        )
    return key


def _key(car: Mapping[str, Any], where: str, base_dir: Path) -> bytes:
    if ("key" in car) == ("key_file" in car):
        raise FleetError(f"{where}: give exactly one of key or key_file")
    if "key" in car:
        if not isinstance(car["key"], str):
            raise FleetError(f"{where}: key must be a hex string")
        return _key_from_text(car["key"], f"{where}: key")
    path = base_dir / str(car["key_file"])
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise FleetError(f"{where}: cannot read key_file {path}: {err.strerror}") from None
    if len(raw) == KEY_BYTES:
        return raw
    try:
        return _key_from_text(raw.decode("ascii"), f"{where}: key_file {path}")
    except UnicodeDecodeError:
        raise FleetError(
            f"{where}: key_file {path} must hold {KEY_BYTES} raw bytes or hex"
        ) from None


def _endpoint(
    car: Mapping[str, Any], where: str, car_id: int, base_port: int | None
) -> tuple[str, int]:
    if "port" in car and "address" in car:
        raise FleetError(f"{where}: give port or address, not both")
    if "address" in car:
        host, sep, port = str(car["address"]).rpartition(":")
        if not sep or not host or not port.isdigit():
            raise FleetError(f"{where}: address must be HOST:PORT, got {car['address']!r}")
        return host, _int(int(port), f"{where}: port", 0, 65535)
    if "port" in car:
        return "127.0.0.1", _int(car["port"], f"{where}: port", 0, 65535)
    if base_port is None:
        raise FleetError(f"{where}: no port or address, and no --base-port")
    return "127.0.0.1", 0 if base_port == 0 else _int(
        base_port + car_id, f"{where}: port", 1, 65535
    )


def parse_fleet(doc: Mapping[str, Any], base_dir: Path, base_port: int | None) -> list[CarSpec]:
    """Validate a parsed fleet document; ``base_port + id`` is the port of cars without one."""
    cars = doc.get("car")
    if not isinstance(cars, list) or not cars:
        raise FleetError("no [[car]] tables")
    specs: list[CarSpec] = []
    for i, car in enumerate(cars, 1):
        where = f"car #{i}"
        if not isinstance(car, dict):
            raise FleetError(f"{where}: must be a table")
        unknown = set(car) - _CAR_FIELDS
        if unknown:
            raise FleetError(f"{where}: unknown field(s) {', '.join(sorted(unknown))}")
        for required in ("id", "marker"):
            if required not in car:
                raise FleetError(f"{where}: missing {required}")
        car_id = _int(car["id"], f"{where}: id", 1, 0xFFFE)
        where = f"car {car_id}"
        marker = _int(car["marker"], f"{where}: marker", 0, 0xFFFF)
        key = _key(car, where, base_dir)
        host, port = _endpoint(car, where, car_id, base_port)
        start = car.get("start", [4, 4])
        if not (isinstance(start, list) and len(start) == 2):
            raise FleetError(f"{where}: start must be [row, col]")
        start_pose = (
            _int(start[0], f"{where}: start row", 0, 0x7FFF),
            _int(start[1], f"{where}: start col", 0, 0x7FFF),
        )
        faults = car.get("faults", {})
        try:
            Faults.from_mapping(faults)
        except (ValueError, AttributeError) as err:
            raise FleetError(f"{where}: faults: {err}") from None
        specs.append(CarSpec(car_id, marker, key, host, port, start_pose, dict(faults)))
    for attr, what in (("car_id", "car id"), ("marker", "marker")):
        values = [getattr(s, attr) for s in specs]
        dup = next((v for v in values if values.count(v) > 1), None)
        if dup is not None:
            raise FleetError(f"duplicate {what} {dup}")
    endpoints = [(s.host, s.port) for s in specs if s.port]
    dup_ep = next((e for e in endpoints if endpoints.count(e) > 1), None)
    if dup_ep is not None:
        raise FleetError(f"duplicate port {dup_ep[1]} on {dup_ep[0]}")
    return specs


def load_fleet(path: str | Path, base_port: int | None = None) -> list[CarSpec]:
    """Read and validate ``path``; every failure is a ``FleetError`` naming the file."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise FleetError(f"cannot read fleet file {path}: {err.strerror}") from None
    except UnicodeDecodeError:
        raise FleetError(f"fleet file {path} is not UTF-8 text") from None
    except tomllib.TOMLDecodeError as err:
        raise FleetError(f"fleet file {path}: malformed TOML: {err}") from None
    try:
        return parse_fleet(doc, path.parent, base_port)
    except FleetError as err:
        raise FleetError(f"fleet file {path}: {err}") from None
