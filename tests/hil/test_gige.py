"""The closed loop through a real GigE Vision stream: ``udan-hil run --camera gige`` serves the
world's rendered frames from Aravis's fake GigE camera on loopback, ``udan-edge`` reads them as
``aravis://127.0.0.1`` and drives the mock cars. One run carries every camera fault: frames held
5 ms in every other second, stream packets lost (about a fifth of the frames incomplete), and the
camera unplugged for two seconds; the edge's flight recording is checked against the world's
truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_loop import run_hil, telemetry

from udan.hil.harness import DELAY_BLOCK_S

pytestmark = pytest.mark.hil

DELAY_MS = 5.0
BLOCK_NS = round(DELAY_BLOCK_S * 1e9)
UNPLUG = (2.0, 12.0)  # for, at (s)


def test_the_loop_through_a_gige_camera_with_its_faults(tmp_path: Path) -> None:
    seconds, at = UNPLUG
    s = run_hil(
        tmp_path, "--camera", "gige", "--record", "--cars", "1-3", "--obstacles", "0-2",
        "--duration", "30", "--faults",
        f"frame_delay={DELAY_MS:g}ms,gige_loss=1.35e-4,unplug={seconds:g}s@{at:g}s",
    )  # fmt: skip
    head, camera = s["headline"], s["edge"]["camera"]
    assert head["exits"] == {"world": 0, "gige": 0, "edge": 0}
    assert head["late_executions"] == 0 and head["collisions"] == 0
    # a loaded machine holds the edge between the dispatcher's cut-off and its syscall now and
    # then (test_loop allows one a run); with the fake camera's stream on the same two cores
    # (66,000 packets a second each way) and a load of 12-15, up to a tenth of the commands
    # were (counted, and refused by the car: never executed late); 0 on a quiet machine
    commands = s["edge"]["counts"]["on_time"] + head["commands_missed"]
    assert head["late_sends"] <= max(1, 0.2 * commands)
    assert camera["mode"]["clock"] == "realtime" and camera["warnings"] == []
    # on a quiet machine every command is on time; a saturated 2-core one (the fake camera's
    # packets, the world's renderer, the edge and a training all on it) delays the mock cars'
    # loops past a deadline now and then: missed, never executed late
    assert head["commands_on_time_share"] >= 0.5 and head["steps"] > 50

    # packets lost: about a fifth of the frames came incomplete; counted, never analysed
    offered = camera["captured"] + camera["stale"] + camera["incomplete"]
    assert 0.08 <= camera["incomplete"] / offered <= 0.4, camera
    # and no confident sighting put a car in a cell it was not in (the recording against the
    # world's truth)
    assert s["sightings"]["sightings"] > 200 and s["sightings"]["wrong"] == 0

    records = telemetry(tmp_path)
    unplug = next(e for e in s["events"] if e["kind"] == "unplug")
    out = (unplug["t_ns"], unplug["back_ns"] + 3e9)  # the outage and the reconnection

    # frames held 5 ms before they were sent are 5 ms older on arrival: held and not held
    # alternate every tenth of a second (frames within 5 ms of a block's edge left out), and
    # the shift between the two is the median of their pairwise differences (Hodges-Lehmann)
    ages: dict[bool, list[float]] = {True: [], False: []}
    for r in (r for r in records if r["kind"] == "frame"):
        t = r["t_ns"]
        if not out[0] <= t <= out[1] and 5e6 < t % BLOCK_NS < BLOCK_NS - 5e6:
            ages[(t // BLOCK_NS) % 2 == 0].append(r["age_ns"] / 1e6)
    assert min(map(len, ages.values())) > 100
    held = float(np.median(np.subtract.outer(ages[True], ages[False])))
    assert abs(held - DELAY_MS) <= 1.0, held

    # unplugged: no step while it was gone, the reason in telemetry, driving again after
    lost = [r for r in records if r["kind"] == "camera_lost"]
    back = [r for r in records if r["kind"] == "camera_back"]
    assert len(lost) == 1 and len(back) == 1
    assert lost[0]["reason"] == "GenICam camera 127.0.0.1 lost: no complete frame for 1 s"
    steps = [r["t_ns"] for r in records if r["kind"] == "step"]
    # (the camera's return is in telemetry before the step its first frames decide)
    gone = [t for t in steps if unplug["t_ns"] + 0.2e9 < t < back[0]["t_ns"]]
    assert not gone, [(t - unplug["t_ns"]) / 1e9 for t in gone] + [lost[0], back[0]]
    # driving again in the 16 s left after the camera's return (a loaded machine, the suite and
    # a training beside it, made 19 steps there once an episode's first step waits two sweeps)
    assert sum(t > back[0]["t_ns"] for t in steps) > 10
