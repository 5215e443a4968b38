"""Which cars are driven right now, and the policy slot each one holds.

A car is in the fleet when it has joined over the protocol (and its clock is synchronised) and
the camera sees its marker. It leaves when its marker has not been seen for ``lost_s`` or when
the link drops it (LEAVE, reboot, silence). The policy keeps recurrent state per slot; a car keeps
its slot for as long as it stays, a new car takes a free slot with fresh memory, and a slot freed
by a leaving car is reused only after the next step (the policy sees it absent for one step
first, which also re-forms any group the leaver was in). The camera updates the fleet every
frame and the runtime decides every few frames, so what happened between two steps (cars that
joined, slots that were freed) is kept until :meth:`Fleet.stepped`. The number of cars changes
from one step to the next without a pause.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field


@dataclass
class Change:
    """What one :meth:`Fleet.update` did."""

    joined: list[int] = field(default_factory=list)
    left: list[int] = field(default_factory=list)


class Fleet:
    """Membership and slots, keyed by car id; ``markers`` maps car id -> marker id."""

    def __init__(self, markers: Mapping[int, int], lost_s: float = 0.5) -> None:
        self.markers = dict(markers)
        self.lost_ns = int(lost_s * 1e9)
        self.slot: dict[int, int] = {}
        self.fresh: set[int] = set()
        self._last_seen: dict[int, int] = {}
        self._freed: set[int] = set()
        self._decided = False  # a step was decided since the last reset

    def stepped(self) -> None:
        """A step was decided with the cars in ``fresh``: they are no longer new, and the slots
        freed before it (the step saw them absent) can be taken again."""
        self.fresh.clear()
        self._freed.clear()
        self._decided = True

    @property
    def size(self) -> int:
        """One past the highest slot in use or held (freed, and not yet seen absent by a
        step)."""
        used = list(self.slot.values()) + list(self._freed)
        return max(used) + 1 if used else 0

    def update(self, seen_markers: Iterable[int], ready: Iterable[int], now_ns: int) -> Change:
        """Fold in one camera frame's markers and the link's ready cars at ``now_ns``."""
        seen = set(seen_markers)
        for car, marker in self.markers.items():
            if marker in seen:
                self._last_seen[car] = now_ns
        ready_set = set(ready)
        change = Change()
        for car in sorted(self.slot):
            lost = now_ns - self._last_seen.get(car, now_ns) > self.lost_ns
            if lost or car not in ready_set:
                slot = self.slot.pop(car)
                if self._decided:  # before any step no policy memory is in the slot
                    self._freed.add(slot)
                self.fresh.discard(car)  # joined and gone again before a step saw it
                change.left.append(car)
        taken = set(self.slot.values()) | self._freed
        for car in sorted(ready_set - self.slot.keys()):
            if car in self.markers and self.markers[car] in seen:
                free = next(s for s in range(len(taken) + 1) if s not in taken)
                self.slot[car] = free
                taken.add(free)
                self.fresh.add(car)
                change.joined.append(car)
        return change

    def reset(self) -> None:
        """Forget every car (a new episode, or after an emergency stop)."""
        self.slot.clear()
        self.fresh.clear()
        self._freed.clear()
        self._last_seen.clear()
        self._decided = False
