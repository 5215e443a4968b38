"""The harness's fault spec: ``loss=0.1,jitter=3ms,reboot=car2@10s,stall=500ms@5s``.

Network faults (``loss``, ``delay``, ``jitter``, ``duplicate``, ``reorder``) apply to every car's
link in both directions from the start (the mock firmware's ``Faults``); timed events happen
once, at a time counted from the first episode's start:

- ``reboot=carN@T``: car N reboots (new session; the edge must re-join it);
- ``stall=D@T``: the camera sends no frame for D;
- ``leave=carN@T``: car N is taken off the arena (the fleet shrinks, the others go on);
- ``join=carN@T``: car N is put on a free cell (the fleet grows);
- ``cut=carN@T``: car N's next move stops half-way, where the car then is (a wheel blocked for
  a moment): the edge must see it across a border and re-centre it;
- ``forge=N@T``: N forged or malformed datagrams to the edge and to every car (random bytes,
  frames with a wrong key, truncated and replayed-looking frames): dropped and counted.

Faults of the GigE Vision camera (``udan-hil run --camera gige``, :mod:`udan.hil.gige`), from
the start: ``gige_loss=P`` drops each stream packet with probability P (lost packets are not
resent: the frame arrives incomplete); ``frame_delay=D`` holds the frames of every other tenth
of a second (on the monotonic clock) for D between their timestamp and their first packet, so
frames held and not held can be compared in one run. And once: ``unplug=D@T``: the camera goes
away at T and comes back D later.

Durations take ``ms`` or ``s``; probabilities are in [0, 1].
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

_NETWORK = {
    "loss": "loss",
    "duplicate": "duplicate",
    "reorder": "reorder",
    "delay": "delay_ms",
    "jitter": "jitter_ms",
}
_PROBABILITIES = {"loss", "duplicate", "reorder"}
_CAMERA = {"gige_loss": "lost_ratio", "frame_delay": "delay_ms"}
_EVENT = re.compile(r"^(?:car(?P<car>\d+)|(?P<dur>[\d.]+m?s)|(?P<count>\d+))@(?P<at>[\d.]+m?s)$")


class FaultSpecError(ValueError):
    """A fault spec that does not parse, with a one-line reason."""


@dataclass(frozen=True)
class Event:
    """A fault that happens once: ``kind`` at ``at_s`` for ``car`` (or lasting ``seconds``)."""

    kind: str
    at_s: float
    car: int | None = None
    seconds: float | None = None
    count: int | None = None


@dataclass
class FaultPlan:
    """Network faults for every car and the timed events."""

    network: dict[str, float] = field(default_factory=dict)
    events: list[Event] = field(default_factory=list)
    camera: dict[str, float] = field(default_factory=dict)
    """Faults of the GigE camera (``lost_ratio``, ``delay_ms``)."""


def seconds(text: str, what: str) -> float:
    """``3ms`` / ``0.5s`` -> seconds."""
    match = re.fullmatch(r"([\d.]+)(ms|s)", text.strip())
    if match is None:
        raise FaultSpecError(f"{what}: {text!r} is not a duration like 3ms or 0.5s")
    value = float(match.group(1))
    return value / 1000 if match.group(2) == "ms" else value


def _probability(name: str, value: str) -> float:
    try:
        p = float(value)
    except ValueError:
        raise FaultSpecError(f"{name}={value}: not a probability") from None
    if not 0.0 <= p <= 1.0:
        raise FaultSpecError(f"{name}={value}: not a probability in [0, 1]")
    return p


def parse_faults(spec: str | None) -> FaultPlan:
    """Parse a comma-separated fault spec (empty or None: no faults)."""
    plan = FaultPlan()
    for item in filter(None, (s.strip() for s in (spec or "").split(","))):
        name, sep, value = item.partition("=")
        if not sep or not value:
            raise FaultSpecError(f"fault {item!r} is not NAME=VALUE")
        if name in _NETWORK:
            if name in _PROBABILITIES:
                plan.network[_NETWORK[name]] = _probability(name, value)
            else:
                plan.network[_NETWORK[name]] = seconds(value, name) * 1000
            continue
        if name == "gige_loss":
            plan.camera[_CAMERA[name]] = _probability(name, value)
            continue
        if name == "frame_delay":
            plan.camera[_CAMERA[name]] = seconds(value, name) * 1000
            continue
        match = _EVENT.match(value)
        if name in ("reboot", "leave", "join", "cut") and match and match.group("car"):
            plan.events.append(Event(name, seconds(match["at"], name), car=int(match["car"])))
        elif name in ("stall", "unplug") and match and match.group("dur"):
            plan.events.append(
                Event(name, seconds(match["at"], name), seconds=seconds(match["dur"], name))
            )
        elif name == "forge" and match and match.group("count"):
            plan.events.append(Event(name, seconds(match["at"], name), count=int(match["count"])))
        else:
            raise FaultSpecError(
                f"unknown or malformed fault {item!r} (known: {', '.join(_NETWORK)}, "
                "reboot=carN@T, leave=carN@T, join=carN@T, cut=carN@T, stall=D@T, forge=N@T; with "
                "--camera gige: gige_loss, frame_delay, unplug=D@T)"
            )
    return plan
