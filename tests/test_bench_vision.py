"""The harness of bench/vision.py, whose condition table docs/vision.md quotes: the cars' walks
are ones real cars could drive, and a short run of a condition scores what it says."""

from __future__ import annotations

import math

import benches
import cv2
import numpy as np
import pytest

from udan.edge.geometry import ArenaGeometry, square

bench = benches.load("vision")
GEOMETRY = ArenaGeometry()


@pytest.mark.parametrize("footprint", [bench.CAR_BODY_M, 0.32])
def test_walks_step_from_cell_to_cell_and_stand_still_apart(footprint):
    """Moves take MOVE_FRAMES, then every car stands still, a few centimetres off its cell's
    centre; no two cars' footprints (bodies, or labels of markers printed twice as large)
    overlap at rest; some cars move every step."""
    poses, still = bench.walks(GEOMETRY, 5, 320, seed=3, footprint_m=footprint)
    period = bench.MOVE_FRAMES + bench.REST_FRAMES
    moved = 0
    for start in range(0, 320, period):
        rest = start + bench.MOVE_FRAMES - 1
        assert still[rest : start + period].all()
        assert (poses[rest : start + period] == poses[rest]).all()
        moved += int((~still[start]).sum())
        cells = GEOMETRY.cell_of(poses[rest, :, :2])
        centres = (cells[:, ::-1] + 0.5) * GEOMETRY.cell_m
        assert np.abs(poses[rest, :, :2] - centres).max() <= bench.END_LIMIT_M + 1e-9
        assert len({tuple(c) for c in cells.tolist()}) == 5
        for a in range(5):
            for b in range(a):
                one, other = (
                    square(poses[rest, k, :2], footprint, poses[rest, k, 2]).astype(np.float32)
                    for k in (a, b)
                )
                assert cv2.intersectConvexConvex(one, other)[0] == 0
    assert moved > 20


def test_a_short_condition_run_scores_sightings_against_the_truth():
    """Sixty frames of the 60 degree condition: every still car found in its cell, no wrong
    cell, sightings and CPU times counted (the first two sweeps' frames timed too)."""
    condition = next(c for c in bench.CONDITIONS if c.name == "tilt 60°")
    row = bench.run_condition(condition, GEOMETRY, 60)
    ours, theirs = row["vision"], row["opencv"]
    assert ours["found_pct"] == 100.0 and ours["wrong_cells"] == 0
    assert ours["sightings"] >= 0.95 * 5 * (60 - 24)
    assert ours["median_error_mm"] < 5 and ours["p99_cpu_ms"] > 0
    assert theirs["sightings"] > 0 and math.isfinite(theirs["p99_cpu_ms"])
    verdicts = bench.verdicts([row])
    assert verdicts["found"] and verdicts["no_wrong_cell"]
    assert not verdicts["sightings_for_no_wrong_cell"]  # 10^5 need the full run
