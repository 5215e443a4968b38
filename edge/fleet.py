"""Which cars are driven right now, the policy slot each one holds, where each was seen last and
what it was told last; and :class:`FleetState`, the fleet as one decision step sees it.

A car is in the fleet when it has joined over the protocol (and its clock is synchronised) and
the camera sees its marker. It leaves when its marker has not been seen for ``lost_s`` or when
the link drops it (LEAVE, reboot, silence). The policy keeps recurrent state per slot; a car keeps
its slot for as long as it stays, a new car takes a free slot with fresh memory, and a slot freed
by a leaving car is reused only after the next step (the policy sees it absent for one step
first, which also re-forms any group the leaver was in). The camera updates the fleet every
frame and the runtime decides every few frames, so what happened between two steps (cars that
joined, slots that were freed) is kept until :meth:`Fleet.stepped`. The number of cars changes
from one step to the next without a pause.

:class:`Fleet` is the one owner of the edge's per-car state between steps (the link keeps only
each car's protocol session; the policy's per-slot memory lives in :mod:`udan.edge.decide`,
indexed by the slots given here). Each step reads a :class:`FleetState` snapshot of it: masking,
grouping, the safety filter, dispatch and telemetry all see the same cars, cells and slots.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Set
from dataclasses import dataclass, field

Cell = tuple[int, int]
Seen = tuple[float, float, float, int]
"""Where the camera saw a car: arena metres x, y, heading (radians), and when that frame was
taken (edge clock, ns)."""


@dataclass
class Change:
    """What one :meth:`Fleet.update` did."""

    joined: list[int] = field(default_factory=list)
    left: list[int] = field(default_factory=list)


@dataclass(frozen=True, slots=True)
class FleetState:
    """The fleet at one decision step: built once when the step is due, then read by every
    stage of it and never changed (each mapping is the step's own copy)."""

    slots: Mapping[int, int]
    """Car id -> policy slot, for every car driven this step."""
    fresh: Set[int]
    """Cars new to the policy this step: their memory starts empty."""
    cells: Mapping[int, Cell]
    """Car id -> the cell the camera saw it on last."""
    static: Mapping[str, frozenset[Cell]] = field(default_factory=dict)
    """Cell markers by kind ("obstacle", "wall", "water", and the surround "target")."""
    others: list[Cell] = field(default_factory=list)
    """Cells of markers on the grid that are not cars of the fleet: they block moves."""
    moving: Mapping[int, int] = field(default_factory=dict)
    """Cars still in a move when the step period ran out -> the action they are executing."""
    frame: int = -1
    """Index of the frame the step decides on."""
    t_capture_ns: int = 0
    """When that frame was captured."""
    uncertain: Set[int] = frozenset()
    """Cars the frame could not place in a cell with confidence: held (in `moving` with
    ``wait``) on the cell they were last placed in."""
    calibrated: bool = True
    """Whether the frame's camera model placed anything (if not, every car is uncertain)."""
    poses: Mapping[int, Seen] = field(default_factory=dict)
    """Car id -> where the camera saw it last and when: what its command tells it, so it
    drives from where it is (docs/motion.md)."""


class Fleet:
    """Membership, slots, last cells and last commands, keyed by car id; ``markers`` maps car
    id -> marker id."""

    def __init__(self, markers: Mapping[int, int], lost_s: float = 0.5) -> None:
        self.markers = dict(markers)
        self.car_of_marker = {m: c for c, m in self.markers.items()}
        self.lost_ns = int(lost_s * 1e9)
        self.slot: dict[int, int] = {}
        self.fresh: set[int] = set()
        self.cell: dict[int, Cell] = {}
        """Where each car was last seen on the grid (kept across episodes: the first step of
        the next one is rehearsed from it)."""
        self.pose: dict[int, Seen] = {}
        """Where the camera saw each car last, in metres and radians, and when."""
        self.command: dict[int, int] = {}
        """The last command each car of the fleet was sent."""
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
                self.command.pop(car, None)
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

    def moving(self, finished: Callable[[int], bool]) -> dict[int, int]:
        """Cars whose last move has not ``finished`` -> the action they are executing."""
        return {c: self.command[c] for c in self.slot if c in self.command and not finished(c)}

    def snapshot(
        self,
        static: Mapping[str, frozenset[Cell]],
        others: list[Cell],
        moving: Mapping[int, int],
        frame: int,
        t_capture_ns: int,
        uncertain: Set[int] = frozenset(),
        calibrated: bool = True,
    ) -> FleetState:
        """The fleet as a step decided now sees it."""
        slots = dict(self.slot)
        cells = {c: self.cell[c] for c in slots}
        poses = {c: self.pose[c] for c in slots if c in self.pose}
        return FleetState(
            slots,
            set(self.fresh),
            cells,
            static,
            others,
            moving,
            frame,
            t_capture_ns,
            uncertain,
            calibrated,
            poses,
        )

    def reset(self) -> None:
        """Forget every car but where it was seen (a new episode)."""
        self.slot.clear()
        self.fresh.clear()
        self.command.clear()
        self._freed.clear()
        self._last_seen.clear()
        self._decided = False
