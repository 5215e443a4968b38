"""Faults a mock car can be told to have, and the lossy link that applies the network ones.

Network faults (loss, delay with jitter, duplication, reordering) apply to datagrams in both
directions, each direction drawing from its own seeded generator so a run can be repeated.
Car faults: a reboot after ``reboot_at_s``, a stuck wheel (moves do not happen; the controller
reports a stall), and a dead car after ``dead_at_s`` (it stops answering: nothing in, nothing out).
Times count from when the faults are applied (car start, or a runtime change).
"""

from __future__ import annotations

import asyncio
import random
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

_PROBABILITIES = ("loss", "duplicate", "reorder")


@dataclass
class Faults:
    """Per-car fault settings (all off by default)."""

    loss: float = 0.0
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    reorder_ms: float = 5.0
    reboot_at_s: float | None = None
    stuck_wheel: bool = False
    dead_at_s: float | None = None

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> Faults:
        """Build from a TOML/JSON table; ``ValueError`` names the bad entry."""
        faults = cls()
        faults.update(values)
        return faults

    def update(self, values: Mapping[str, Any]) -> None:
        """Change some settings, checking names, types and ranges first."""
        known = {f.name: f for f in fields(self)}
        checked: dict[str, Any] = {}
        for name, value in values.items():
            if name not in known:
                raise ValueError(f"unknown fault {name!r}; known: {', '.join(known)}")
            if name == "stuck_wheel":
                if not isinstance(value, bool):
                    raise ValueError("stuck_wheel must be true or false")
            elif value is None and name in ("reboot_at_s", "dead_at_s"):
                pass
            elif isinstance(value, bool) or not isinstance(value, int | float) or value < 0:
                raise ValueError(f"fault {name} must be a number >= 0, got {value!r}")
            elif name in _PROBABILITIES and value > 1:
                raise ValueError(f"fault {name} is a probability, got {value!r}")
            checked[name] = value
        for name, value in checked.items():
            setattr(self, name, value)


@dataclass
class LinkStats:
    """What the lossy link did to the datagrams it carried."""

    lost: int = 0
    duplicated: int = 0
    delayed: int = 0


@dataclass
class LossyLink:
    """Delivers datagrams through ``deliver`` after applying the network faults."""

    faults: Faults
    deliver: Callable[[bytes, Any], None]
    rng: random.Random
    stats: LinkStats = field(default_factory=LinkStats)

    def send(self, data: bytes, addr: Any) -> None:
        """Pass one datagram on: maybe dropped, maybe twice, maybe late."""
        f = self.faults
        if f.loss and self.rng.random() < f.loss:
            self.stats.lost += 1
            return
        copies = 1
        if f.duplicate and self.rng.random() < f.duplicate:
            copies = 2
            self.stats.duplicated += 1
        for _ in range(copies):
            delay_ms = f.delay_ms
            if f.jitter_ms:
                delay_ms += self.rng.uniform(-f.jitter_ms, f.jitter_ms)
            if f.reorder and self.rng.random() < f.reorder:
                delay_ms += f.reorder_ms
            if delay_ms <= 0:
                self.deliver(data, addr)
            else:
                self.stats.delayed += 1
                asyncio.get_running_loop().call_later(delay_ms / 1000, self.deliver, data, addr)
