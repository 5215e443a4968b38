"""``udan-hil run`` as a person runs it: it says what it plans, shows its progress, stops on
SIGINT or SIGTERM with a report of what it completed, and leaves no process behind, even when it
is SIGKILLed (its children watch it). Also ``udan-edge --sim``, whose world watches the edge."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from udan.hil.harness import Progress

pytestmark = pytest.mark.hil

BIN = Path(sys.executable).parent
RUN = ["--cars", "2", "--obstacles", "0-4", "--episodes", "2", "--cell-time-ms", "60",
       "--episode-steps", "20"]  # fmt: skip
PLANNED = 10  # 2 per cell, 1 car count x 5 obstacle counts


def _stat(pid: int) -> tuple[int, int, str] | None:
    """(parent pid, start time, state) of a process, None if it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return None
    return int(fields[1]), int(fields[19]), fields[0]


def descendants(root: int) -> dict[int, int]:
    """Every process below ``root`` now: pid -> start time (to tell a reused pid apart)."""
    children: dict[int, list[int]] = {}
    starts = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and (stat := _stat(int(entry.name))) is not None:
            children.setdefault(stat[0], []).append(int(entry.name))
            starts[int(entry.name)] = stat[1]
    found, todo = {}, [root]
    while todo:
        for child in children.get(todo.pop(), []):
            found[child] = starts[child]
            todo.append(child)
    return found


def running(procs: dict[int, int]) -> list[int]:
    """Those of ``procs`` still running (not the same pid reused, not a zombie)."""
    out = []
    for pid, start in procs.items():
        stat = _stat(pid)
        if stat is not None and stat[1] == start and stat[2] != "Z":
            out.append(pid)
    return out


def _wait_gone(procs: dict[int, int], timeout_s: float) -> float:
    """Seconds until none of ``procs`` runs (fails after ``timeout_s``)."""
    start = time.monotonic()
    while running(procs):
        if time.monotonic() - start > timeout_s:
            left = running(procs)
            for pid in left:
                os.kill(pid, signal.SIGKILL)
            raise AssertionError(f"still running after {timeout_s} s: {left}")
        time.sleep(0.02)
    return time.monotonic() - start


def _start(folder: Path) -> tuple[subprocess.Popen, dict[int, int]]:
    """The harness, once its first episode is done; it and every process below it."""
    proc = subprocess.Popen(
        [str(BIN / "udan-hil"), "run", *RUN, "--report", str(folder)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    telemetry = folder / "telemetry.jsonl"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if telemetry.exists() and '"kind":"episode"' in telemetry.read_text():
            break
        time.sleep(0.1)
    family = descendants(proc.pid)
    assert proc.poll() is None and len(family) >= 4, family  # world, camera, edge, perception
    return proc, family


@pytest.mark.parametrize(
    "sig", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)]
)
def test_a_signal_stops_the_run_within_two_seconds_with_a_partial_report(
    tmp_path: Path, sig: signal.Signals
) -> None:
    proc, family = _start(tmp_path)
    proc.send_signal(sig)
    stopped_s = _wait_gone(family, 20.0)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + sig
    assert stopped_s <= 2.0, stopped_s  # every process of the run, the edge first
    lines = err.splitlines()
    assert lines[0].startswith(f"udan-hil: {PLANNED} episodes planned (2 per cell"), lines
    summary = json.loads((tmp_path / "summary.json").read_text())
    head = summary["headline"]
    assert head["interrupted"] == sig.name and head["episodes_planned"] == PLANNED
    assert 1 <= head["episodes"] < PLANNED
    assert len(summary["episodes"]) == head["episodes"]  # each with its pure-simulation score
    assert head["exits"] == {"world": 0, "edge": 0}
    assert f"stopped by {sig.name} after {head['episodes']} of {PLANNED} episodes" in err
    assert json.loads(out)["episodes"] == head["episodes"]
    assert f"Stopped by {sig.name}" in (tmp_path / "report.html").read_text()


def test_a_sigkilled_harness_leaves_no_process_of_its_run(tmp_path: Path) -> None:
    proc, family = _start(tmp_path)
    proc.kill()
    proc.wait()
    _wait_gone(family, 15.0)


@pytest.mark.slow
def test_a_sigkilled_sim_edge_leaves_no_world(tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [str(BIN / "udan-edge"), "--sim", "--cars", "2", "--duration", "60", "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    deadline = time.monotonic() + 60
    while len(family := descendants(proc.pid)) < 3 and time.monotonic() < deadline:
        time.sleep(0.1)  # world, its camera, the perception process
    time.sleep(1.0)
    family = descendants(proc.pid)
    assert len(family) >= 3, family
    proc.kill()
    proc.wait()
    _wait_gone(family, 15.0)


def test_progress_counts_episodes_and_commands_from_the_telemetry_as_it_grows(tmp_path):
    telemetry = tmp_path / "telemetry.jsonl"
    stream = io.StringIO()
    progress = Progress(planned=4, duration_s=None, stream=stream)
    step = {"kind": "step", "on_time": 3, "missed": 1}
    telemetry.write_text(json.dumps(step) + "\n" + json.dumps({"kind": "episode"}) + "\n")
    with telemetry.open("a") as f:
        f.write(json.dumps(step)[:10])  # a line half written
    progress.read(telemetry)
    assert (progress.episodes, progress.on_time, progress.missed) == (1, 3, 1)
    with telemetry.open("a") as f:
        f.write(json.dumps(step)[10:] + "\n")
    progress.read(telemetry)
    assert (progress.episodes, progress.on_time, progress.missed) == (1, 6, 2)
    line = progress.line(elapsed=30.0)
    assert line == "1/4 episodes, 01:30 left, commands on time 75.00 %"
    by_time = Progress(planned=None, duration_s=60.0, stream=stream)
    assert by_time.line(elapsed=15.0) == "0 episodes, 00:45 left, commands on time -"
