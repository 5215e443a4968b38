"""How real cars move in the HIL world: motion-error levels, each car's errors, body contacts.

A car's controller (:class:`udan.firmware_mock.motor.Drive`) plans a straight move in its own
belief; :class:`CarMotion` turns that plan into where the car really goes. The error of a move
has the two parts Borenstein and Feng separate for wheeled odometry (UMBmark): systematic, a
bias per car drawn once (wheel radii, a motor that runs faster), and non-systematic, drawn per
move (floor, roller contact, dust): a distance scale, a loss on the sideways part of a move
(mecanum rollers slip more sideways than rolling forwards), a cross-track drift and a heading
drift growing with the distance driven, an error on commanded turns, and now and then a slip
that loses part of the move. Closed-loop wheel encoders keep a car from overshooting by more
than its scale error: slips and roller losses only ever shorten a move. The figures of each
level, and where they come from, are in docs/motion.md; ``tests/test_motion.py`` holds the
model to them.

Level ``0`` is the exact car of the earlier HIL: constant speed, and every move ends exactly on
the centre of the cell its target lies in, heading as told.

Contacts: each car's body is a square (``CAR_BODY_M``, as rendered) at its true pose; two
bodies that overlap touch (separating-axis test on the two squares' edge directions).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from udan.envs.errors import EnvConfigError
from udan.firmware_mock.motor import Pose, Trajectory, wrap
from udan.hil.render import CAR_BODY_M
from udan.profile import travelled

_HALF_DIAGONAL = CAR_BODY_M / math.sqrt(2)
Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class MotionLevel:
    """How far real moves stray from the planned ones (docs/motion.md gives every figure).

    Distances are scaled by the planned distance; "per cell" figures grow with the distance
    driven over a cell's side; ``bias`` figures are the spread of one car's own systematic error
    (drawn once per car), the others are drawn per move.
    """

    name: str
    accel_share: float = 0.0
    """Share of a move's time spent accelerating (as long braking); 0: constant speed."""
    scale_sd: float = 0.0
    """Distance scale error per move (wheel encoders, tyre and roller deformation)."""
    scale_bias: float = 0.0
    """A car's own distance scale error (its wheels' radii against the nominal)."""
    strafe_loss: float = 0.0
    """Mean share of a sideways move lost (mecanum rollers slip more sideways than rolling)."""
    strafe_loss_sd: float = 0.0
    """Its spread per move (never a gain: a loss below 0 is 0)."""
    drift_sd: float = 0.0
    """Cross-track drift, metres per metre driven, per move."""
    drift_bias: float = 0.0
    """A car's own cross-track drift, metres per metre."""
    heading_sd_deg: float = 0.0
    """Heading drift per cell driven, per move (degrees)."""
    heading_bias_deg: float = 0.0
    """A car's own heading drift per cell driven (degrees)."""
    turn_sd: float = 0.0
    """Scale error of a commanded turn, per move."""
    slip_probability: float = 0.0
    """Chance that a move slips."""
    slip_loss: tuple[float, float] = (0.0, 0.0)
    """Share of the move a slip loses (uniform in this range)."""

    @property
    def exact(self) -> bool:
        """Moves end exactly where they are planned to (level ``0``)."""
        return self == MotionLevel(self.name, self.accel_share)


LEVELS = {
    "0": MotionLevel("0"),
    "low": MotionLevel(
        "low", accel_share=0.25, scale_sd=0.01, scale_bias=0.005, strafe_loss=0.02,
        strafe_loss_sd=0.01, drift_sd=0.01, drift_bias=0.005, heading_sd_deg=0.5,
        heading_bias_deg=0.25, turn_sd=0.02,
    ),
    "lab": MotionLevel(
        "lab", accel_share=0.25, scale_sd=0.02, scale_bias=0.01, strafe_loss=0.05,
        strafe_loss_sd=0.02, drift_sd=0.03, drift_bias=0.01, heading_sd_deg=1.5,
        heading_bias_deg=0.5, turn_sd=0.05, slip_probability=0.01, slip_loss=(0.2, 0.5),
    ),
    "rough": MotionLevel(
        "rough", accel_share=0.25, scale_sd=0.03, scale_bias=0.02, strafe_loss=0.10,
        strafe_loss_sd=0.04, drift_sd=0.04, drift_bias=0.015, heading_sd_deg=3.0,
        heading_bias_deg=1.0, turn_sd=0.10, slip_probability=0.05, slip_loss=(0.3, 0.8),
    ),
}  # fmt: skip


def motion_level(name: str) -> MotionLevel:
    """The level called ``name``; ``EnvConfigError`` (one line) for an unknown one."""
    try:
        return LEVELS[name]
    except KeyError:
        raise EnvConfigError(
            f"unknown motion level {name!r} (choose from {', '.join(LEVELS)})"
        ) from None


def forward(heading: float) -> tuple[float, float]:
    """Unit vector a car facing ``heading`` drives forwards along (0 faces -y, clockwise)."""
    return math.sin(heading), -math.cos(heading)


@dataclass(frozen=True, slots=True)
class MoveError:
    """What one move did wrong, in the car's own frame: scale of the distance, share of the
    sideways part lost, cross-track drift (metres per metre), heading drift (radians per
    cell), turn scale, and the share a slip lost (0: none)."""

    scale: float
    strafe_loss: float
    drift: float
    heading_per_cell: float
    turn_scale: float
    slip: float


class CarMotion:
    """One car's errors: its systematic biases, and a per-move draw, from its own seeded
    generator (the world seeds it with the run's seed and the car's id)."""

    def __init__(self, level: MotionLevel, seed: int, car_id: int, cell_m: float) -> None:
        self.level = level
        self.cell_m = cell_m
        self.rng = np.random.default_rng([seed, car_id])
        bias = self.rng.standard_normal(3)
        self.scale_bias = level.scale_bias * float(bias[0])
        self.drift_bias = level.drift_bias * float(bias[1])
        self.heading_bias = math.radians(level.heading_bias_deg) * float(bias[2])
        self.slips = 0

    def draw(self) -> MoveError:
        """The error of the next move (always the same number of draws, so one car's stream
        depends only on how many moves it made)."""
        lv = self.level
        n = self.rng.standard_normal(5)
        u = self.rng.random(2)
        slipped = u[0] < lv.slip_probability
        return MoveError(
            scale=1 + self.scale_bias + lv.scale_sd * float(n[0]),
            strafe_loss=max(0.0, lv.strafe_loss + lv.strafe_loss_sd * float(n[1])),
            drift=self.drift_bias + lv.drift_sd * float(n[2]),
            heading_per_cell=self.heading_bias + math.radians(lv.heading_sd_deg) * float(n[3]),
            turn_scale=1 + lv.turn_sd * float(n[4]),
            slip=lv.slip_loss[0] + (lv.slip_loss[1] - lv.slip_loss[0]) * float(u[1])
            if slipped
            else 0.0,
        )

    def true_end(self, start: Pose, plan: Trajectory) -> Pose:
        """Where a car truly at ``start`` ends when it drives ``plan`` (planned in its belief:
        it drives the plan's displacement in its own frame, so a belief off in heading drives
        off in direction)."""
        err = self.draw()
        self.slips += err.slip > 0
        dx, dy = plan.end.x - plan.start.x, plan.end.y - plan.start.y
        fx, fy = forward(plan.start.heading)
        ahead, aside = dx * fx + dy * fy, dx * -fy + dy * fx  # forwards, to the right
        dist = math.hypot(ahead, aside)
        keep = err.scale * (1 - err.slip)
        # scaled (the sideways part loses more), then the cross-track drift: drift x distance,
        # to the right of the direction driven
        ahead, aside = (
            keep * (ahead - err.drift * aside),
            keep * (aside * (1 - err.strafe_loss) + err.drift * ahead),
        )
        tx, ty = forward(start.heading)
        turn = wrap(plan.end.heading - plan.start.heading) * err.turn_scale
        turn += err.heading_per_cell * dist * keep / self.cell_m
        return Pose(
            start.x + ahead * tx - aside * ty,
            start.y + ahead * ty + aside * tx,
            wrap(start.heading + turn),
        )


def poses_at(trajectory: Trajectory, times_ns: np.ndarray) -> np.ndarray:
    """(T, 3) poses of ``trajectory`` at ``times_ns`` (:meth:`Trajectory.at`, on arrays)."""
    tau = (np.asarray(times_ns) - trajectory.started_ns) / trajectory.duration_ns
    f = travelled(tau, trajectory.accel_share)
    start = np.asarray(trajectory.start)
    delta = np.asarray(trajectory.end) - start
    delta[2] = wrap(delta[2])
    return start + f[:, None] * delta


def _corners(x: np.ndarray, y: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """(..., 4, 2) corners of bodies centred on (x, y) facing ``heading``."""
    half = CAR_BODY_M / 2
    local = np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
    c, s = np.cos(heading)[..., None], np.sin(heading)[..., None]
    px = x[..., None] + local[:, 0] * c - local[:, 1] * s
    py = y[..., None] + local[:, 0] * s + local[:, 1] * c
    return np.stack([px, py], -1)


def bodies_touch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether bodies at poses ``a`` and ``b`` ((..., 3): x, y, heading) overlap, elementwise."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ca, cb = _corners(*np.moveaxis(a, -1, 0)), _corners(*np.moveaxis(b, -1, 0))
    touch = np.ones(ca.shape[:-2], bool)
    for heading in (a[..., 2], b[..., 2]):
        for axis in (np.stack([np.cos(heading), np.sin(heading)], -1),
                     np.stack([-np.sin(heading), np.cos(heading)], -1)):  # fmt: skip
            pa = np.einsum("...kd,...d->...k", ca, axis)
            pb = np.einsum("...kd,...d->...k", cb, axis)
            touch &= (pa.max(-1) > pb.min(-1)) & (pb.max(-1) > pa.min(-1))
    return touch


def reach_box(trajectory: Trajectory | None, rest: Pose, since_ns: int, now_ns: int) -> Box:
    """(x min, x max, y min, y max) of where a car's centre is between ``since_ns`` and
    ``now_ns``: at ``rest``, or anywhere along its straight move between the two instants."""
    if trajectory is None:
        return rest.x, rest.x, rest.y, rest.y
    a, b = trajectory.at(since_ns), trajectory.at(now_ns)
    return min(a.x, b.x), max(a.x, b.x), min(a.y, b.y), max(a.y, b.y)


def may_meet(a: Box, b: Box) -> bool:
    """Whether two cars whose centres stay within the boxes ``a`` and ``b``
    (:func:`reach_box`) may come close enough to touch (:func:`may_touch`) at all: a cut in
    plain Python before any sampling, which most pairs of an arena never pass."""
    dx = max(0.0, b[0] - a[1], a[0] - b[1])
    dy = max(0.0, b[2] - a[3], a[2] - b[3])
    return math.hypot(dx, dy) < 2 * _HALF_DIAGONAL


def may_touch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Centres close enough for two bodies to touch at some heading (a cheap first cut)."""
    d = np.hypot(a[..., 0] - b[..., 0], a[..., 1] - b[..., 1])
    return d < 2 * _HALF_DIAGONAL
