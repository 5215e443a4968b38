"""fleet.toml (docs/protocol.md section 12): which cars exist, their markers, keys and addresses.

The one reader of the fleet file, in the lowest layer so that both the edge (which cars it may
drive) and the mock firmware (which cars it stands in for) read it with the same rules: every bad
input is one ``FleetFileError`` whose message names the file and the car, so a command can print
one line and exit 2 instead of showing a traceback. Mock-only fields (``start``, ``faults``) are
kept raw in :attr:`CarEntry.mock` and checked by the mock (:mod:`udan.firmware_mock.fleet`): a
setting for simulated cars must not keep the edge from driving real ones.

A car's address is ``address = "HOST:PORT"`` or ``port`` (on 127.0.0.1). A car with neither, or
with port 0 (the mock's "any free port"), has no address until its first authenticated frame
arrives: the UDP transport answers cars where their frames come from.
"""

from __future__ import annotations

import re
import secrets
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

_EDGE_FIELDS = {"id", "marker", "port", "address", "key", "key_file", "serial", "marker_height_m"}
#: Highest a car's marker may sit above the floor (metres): a car's top, not a camera's height.
MAX_MARKER_HEIGHT_M = 1.0
_MOCK_ONLY_FIELDS = {"start", "faults"}
_HEX = re.compile(r"[0-9a-fA-F]*")
#: A car key's length in bytes (its HMAC-SHA256 key, docs/protocol.md section 12).
KEY_BYTES = 32


class FleetFileError(ValueError):
    """A fleet file that cannot be used; the message is one line naming the file and the car."""


@dataclass(frozen=True)
class CarEntry:
    """One car of the fleet: its ids, its key and where to reach it (None: learned from its
    frames, or for the mock a port from ``--base-port``)."""

    car_id: int
    marker: int
    key: bytes = field(repr=False)
    host: str | None = None
    port: int | None = None
    serial: str | None = None  # device of the car's wired serial link (serial transport)
    mock: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)
    """The mock-only fields as written (``start``, ``faults``): the mock checks them."""
    marker_height_m: float = 0.0
    """How far the car's marker sits above the floor (on top of the car): the vision maps it
    through that plane, or the parallax puts the car centimetres off near the image's edges."""

    @property
    def address(self) -> tuple[str, int] | None:
        """UDP address from the fleet file; None: learned from the car's frames."""
        return None if self.host is None or not self.port else (self.host, self.port)


def _int(value: Any, what: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise FleetFileError(f"{what} must be an integer in {lo}-{hi}, got {value!r}")
    return value


def _hex_key(text: str, what: str) -> bytes:
    text = text.strip()
    if not _HEX.fullmatch(text) or len(text) % 2:
        raise FleetFileError(f"{what} is not hex")
    key = bytes.fromhex(text)
    if len(key) != KEY_BYTES:
        raise FleetFileError(
            f"{what} must be {KEY_BYTES} bytes ({2 * KEY_BYTES} hex digits), got {len(key)} bytes"
        )
    return key


def _key(car: Mapping[str, Any], where: str, base_dir: Path) -> bytes:
    if ("key" in car) == ("key_file" in car):
        raise FleetFileError(f"{where}: give exactly one of key or key_file")
    if "key" in car:
        if not isinstance(car["key"], str):
            raise FleetFileError(f"{where}: key must be a hex string")
        return _hex_key(car["key"], f"{where}: key")
    if not isinstance(car["key_file"], str):
        raise FleetFileError(f"{where}: key_file must be a path string")
    path = base_dir / car["key_file"]
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise FleetFileError(f"{where}: cannot read key_file {path}: {err.strerror}") from None
    if len(raw) == KEY_BYTES:
        return raw
    try:
        return _hex_key(raw.decode("ascii"), f"{where}: key_file {path}")
    except UnicodeDecodeError:
        raise FleetFileError(
            f"{where}: key_file {path} must hold {KEY_BYTES} raw bytes or hex"
        ) from None


def _endpoint(car: Mapping[str, Any], where: str) -> tuple[str | None, int | None]:
    if "port" in car and "address" in car:
        raise FleetFileError(f"{where}: give port or address, not both")
    if "address" in car:
        host, sep, port = str(car["address"]).rpartition(":")
        if not sep or not host or not port.isdigit():
            raise FleetFileError(f"{where}: address must be HOST:PORT, got {car['address']!r}")
        return host.strip("[]"), _int(int(port), f"{where}: port", 0, 65535)
    if "port" in car:
        return "127.0.0.1", _int(car["port"], f"{where}: port", 0, 65535)
    return None, None


def _entry(car: Any, index: int, base_dir: Path) -> CarEntry:
    where = f"car #{index}"
    if not isinstance(car, dict):
        raise FleetFileError(f"{where}: must be a table")
    unknown = set(car) - _EDGE_FIELDS - _MOCK_ONLY_FIELDS
    if unknown:
        raise FleetFileError(f"{where}: unknown field(s) {', '.join(sorted(unknown))}")
    for required in ("id", "marker"):
        if required not in car:
            raise FleetFileError(f"{where}: missing {required}")
    car_id = _int(car["id"], f"{where}: id", 1, 0xFFFE)
    where = f"car {car_id}"
    marker = _int(car["marker"], f"{where}: marker", 0, 0xFFFF)
    key = _key(car, where, base_dir)
    host, port = _endpoint(car, where)
    device = car.get("serial")
    if device is not None and (not isinstance(device, str) or not device):
        raise FleetFileError(f"{where}: serial must be a device path, got {device!r}")
    height = car.get("marker_height_m", 0.0)
    if (
        isinstance(height, bool)
        or not isinstance(height, int | float)
        or not 0 <= height <= MAX_MARKER_HEIGHT_M
    ):
        raise FleetFileError(
            f"{where}: marker_height_m must be metres in 0-{MAX_MARKER_HEIGHT_M}, got {height!r}"
        )
    mock = {name: car[name] for name in _MOCK_ONLY_FIELDS if name in car}
    return CarEntry(car_id, marker, key, host, port, device, mock, float(height))


def _first_duplicate(values: list[Any]) -> Any:
    seen: set[Any] = set()
    for value in values:
        if value in seen:
            return value
        seen.add(value)
    return None


def parse_fleet(doc: Mapping[str, Any], base_dir: Path) -> list[CarEntry]:
    """Validate a parsed fleet document (``key_file`` paths are relative to ``base_dir``)."""
    cars = doc.get("car")
    if not isinstance(cars, list) or not cars:
        raise FleetFileError("no [[car]] tables")
    entries = [_entry(car, i, base_dir) for i, car in enumerate(cars, 1)]
    checks = (
        ("car id", [e.car_id for e in entries]),
        ("marker", [e.marker for e in entries]),
        ("port", [e.address for e in entries if e.address is not None]),
        ("serial device", [e.serial for e in entries if e.serial is not None]),
    )
    for what, values in checks:
        dup = _first_duplicate(values)
        if dup is not None:
            shown = f"{dup[1]} on {dup[0]}" if isinstance(dup, tuple) else dup
            raise FleetFileError(f"duplicate {what} {shown}")
    return entries


def load_fleet(path: str | Path) -> list[CarEntry]:
    """Read and validate ``path``; every failure is a ``FleetFileError`` naming the file."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise FleetFileError(f"cannot read fleet file {path}: {err.strerror}") from None
    except UnicodeDecodeError:
        raise FleetFileError(f"fleet file {path} is not UTF-8 text") from None
    except tomllib.TOMLDecodeError as err:
        raise FleetFileError(f"fleet file {path}: malformed TOML: {err}") from None
    try:
        return parse_fleet(doc, path.parent)
    except FleetFileError as err:
        raise FleetFileError(f"fleet file {path}: {err}") from None


def write_fleet(path: Path, cars: int, marker_base: int = 10) -> Path:
    """A fleet file for cars 1..``cars`` (markers ``marker_base`` + id) with fresh random keys
    and no address: the stand-in cars bind any free port and the edge learns it from their
    authenticated JOINs (``--sim``, the HIL harness, tests)."""
    path.write_text(
        "".join(
            f'[[car]]\nid = {c}\nmarker = {marker_base + c}\nkey = "{secrets.token_hex(32)}"\n\n'
            for c in range(1, cars + 1)
        ),
        encoding="utf-8",
    )
    return path
