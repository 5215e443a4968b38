"""Whether each car marker sits at the height the fleet file says (`marker_height_m`).

The vision maps a car marker to the floor through the plane at its told height. A marker that
is in fact higher (on top of a car the fleet file leaves at the default 0) lands off by
``(H - told) / (H - true) - 1`` of its distance from the point under the camera (``H``: the
camera's height): 10 cm up under a camera 3 m up is 7 cm at the arena's corners, and under a
camera tilted 60 degrees, 1.6 m up, a cell or more, in the wrong cell with full confidence.
Through that plane the marker's size is off by the same ratio, and the size does not depend on
where the car stands or how it is driven (a controller that centres cars by their measured
positions hides any offset pattern), so that is what is checked: the side of the marker's
corners refined at full resolution (the tracked corners, fitted to contours, read about 5 %
small), mapped through the told plane, against the configured side, over sightings of the car
standing still, with the lens's calibration file (without it the camera's height is only an
estimate).

A marker printed larger or smaller than configured looks the same as one higher or lower: the
warning names both causes. One whose size implies no possible height (below the floor, or more
than a metre up) was printed at another size, and its height cannot be told from its size.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

SAMPLES = 30
"""Sightings of a car over which its marker's size is taken (their median)."""
TOLERANCE_M = 0.05
"""Height disagreement warned about. Rendered frames (noise, blur, tilt 0-60 degrees) read a
marker at its told height as 0.7 % small: 2 cm under a camera 3 m up."""
HIGHEST_M = 1.0
"""The highest marker a fleet file may give; a size implying more is a print size."""
LOWEST_M = -0.05
"""A size implying a marker lower than this below the floor is a print size."""


class HeightCheck:
    """Collects each car marker's apparent size and says, once per car, when it disagrees
    with the fleet file's height."""

    def __init__(self, told: Mapping[int, float], side_m: float) -> None:
        self._told = dict(told)
        self._side_m = side_m
        self._ratios: dict[int, list[float]] = {}
        self.done: set[int] = set()
        """Cars whose marker has been judged (warned about, or found where it should be)."""

    def told(self, marker: int) -> float:
        """The marker's height in the fleet file (metres; 0 when it gives none)."""
        return self._told.get(marker, 0.0)

    def add(self, marker: int, side_m: float, camera_height_m: float, reach_m: float) -> str | None:
        """One sighting: the marker's mean side (metres) through the plane at its told height,
        seen by a camera `camera_height_m` up whose foot is at most `reach_m` from the grid.
        Returns the one-line warning when the car's SAMPLES-th sighting shows a disagreement,
        else None."""
        if marker in self.done:
            return None
        ratios = self._ratios.setdefault(marker, [])
        ratios.append(side_m / self._side_m)
        if len(ratios) < SAMPLES:
            return None
        self.done.add(marker)
        ratio = float(np.median(ratios))
        told = self.told(marker)
        # through the told plane a marker at height h reads (H - told) / (H - h) of its size,
        # and lands as much farther from the camera's foot
        implied = camera_height_m - (camera_height_m - told) / ratio
        if not LOWEST_M <= implied <= HIGHEST_M:
            return (
                f"car marker {marker} looks {ratio:.2f}x its configured "
                f"{self._side_m:.3f} m side: printed at another size, so its height "
                f"(marker_height_m {told:.2f} m) cannot be checked"
            )
        if abs(implied - told) <= TOLERANCE_M:
            return None
        return (
            f"car marker {marker} looks {ratio:.3f}x its configured {self._side_m:.3f} m side "
            f"through its marker_height_m {told:.2f} m: it sits about {implied:.2f} m high (or "
            f"was printed {ratio * self._side_m:.3f} m); set its marker_height_m in the fleet "
            f"file, or it may be placed up to {abs(ratio - 1) * reach_m:.2f} m off"
        )
