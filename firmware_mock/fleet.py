"""The fleet as the mock firmware needs it: the shared fleet-file reader (:mod:`udan.fleetfile`)
plus what only a simulated car has — a port when the file gives none, a starting cell, faults.

Every problem is one :class:`udan.fleetfile.FleetFileError` naming the file and the car, so the
CLI can print it and exit 2 instead of showing a traceback.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from udan.firmware_mock.faults import Faults
from udan.fleetfile import CarEntry, FleetFileError
from udan.fleetfile import load_fleet as load_entries

DEFAULT_START = (4, 4)


@dataclass(frozen=True)
class CarSpec:
    """One car of the fleet as the mock firmware needs it."""

    car_id: int
    marker: int
    key: bytes = field(repr=False)
    host: str = "127.0.0.1"
    port: int = 0
    start: tuple[int, int] = DEFAULT_START
    faults: Mapping[str, Any] = field(default_factory=dict)


def _cell_part(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0x7FFF:
        raise FleetFileError(f"{what} must be an integer in 0-32767, got {value!r}")
    return value


def _spec(entry: CarEntry, base_port: int | None) -> CarSpec:
    """The mock's car from a fleet-file entry; ``base_port + id`` for a car without a port."""
    where = f"car {entry.car_id}"
    host, port = entry.host, entry.port
    if port is None:
        if base_port is None:
            raise FleetFileError(f"{where}: no port or address, and no --base-port")
        host, port = "127.0.0.1", 0 if base_port == 0 else base_port + entry.car_id
        if port > 65535:
            raise FleetFileError(f"{where}: port must be an integer in 1-65535, got {port!r}")
    start = entry.mock.get("start", list(DEFAULT_START))
    if not (isinstance(start, list) and len(start) == 2):
        raise FleetFileError(f"{where}: start must be [row, col]")
    row, col = (
        _cell_part(start[0], f"{where}: start row"),
        _cell_part(start[1], f"{where}: start col"),
    )
    faults = entry.mock.get("faults", {})
    try:
        Faults.from_mapping(faults)
    except (ValueError, AttributeError) as err:
        raise FleetFileError(f"{where}: faults: {err}") from None
    host = host or "127.0.0.1"
    return CarSpec(entry.car_id, entry.marker, entry.key, host, port, (row, col), dict(faults))


def load_fleet(path: str | Path, base_port: int | None = None) -> list[CarSpec]:
    """Read and validate ``path`` for the mock; every failure is a ``FleetFileError`` naming the
    file."""
    entries = load_entries(path)
    try:
        specs = [_spec(entry, base_port) for entry in entries]
        endpoints = [(s.host, s.port) for s in specs if s.port]
        dup = next((e for e in endpoints if endpoints.count(e) > 1), None)
        if dup is not None:
            raise FleetFileError(f"duplicate port {dup[1]} on {dup[0]}")
    except FleetFileError as err:
        raise FleetFileError(f"fleet file {path}: {err}") from None
    return specs
