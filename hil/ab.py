"""Interleaved A/B blocks of ``udan-edge --sim`` runs, read as the project reads ratios
(docs/targets.md): blocks alternate A, B, A, B, ... on the same machine, each a fresh run; the
decision latency of a block is every step's ``state_to_commands`` after its warm-up; the ratio is
p99(B) / p99(A) over every step of each arm, with a 95 % CI from resampling the pairs of blocks.
A bench names what B adds (``--record``, ``--web``) and reads the rest of each run's report.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

UDAN_EDGE = str(Path(sys.executable).with_name("udan-edge"))
BOOTSTRAP = 2000


@dataclass
class Block:
    """One run: its decision latencies after the warm-up, its deadline counts, its report."""

    decisions_ns: np.ndarray
    on_time: int
    missed: int
    report: dict[str, Any] = field(repr=False)


def sim_command(extra: Sequence[str], folder: Path, seconds: float, realtime: bool) -> list[str]:
    """``udan-edge --sim --cars 5`` for ``seconds`` with ``extra`` arguments, writing its
    telemetry and report into ``folder`` (:func:`read_block` reads them)."""
    cmd = [UDAN_EDGE, "--sim", "--cars", "5", "--duration", str(seconds), "--quiet",
           "--telemetry", str(folder / "telemetry.jsonl"), "--report",
           str(folder / "report.json"), *extra]  # fmt: skip
    return cmd + (["--realtime"] if realtime else [])


def read_block(folder: Path, started_ns: int, warm_up_s: float) -> Block:
    """A finished run's block: every step's decision latency from ``warm_up_s`` after it
    started, its deadline counts, its report."""
    warm_ns = started_ns + int(warm_up_s * 1e9)
    lines = (folder / "telemetry.jsonl").read_text().splitlines()
    records = (json.loads(line) for line in lines)
    decisions = [
        r["state_to_commands_ns"] for r in records if r["kind"] == "step" and r["t_ns"] >= warm_ns
    ]
    result = json.loads((folder / "report.json").read_text())
    counts = result["counts"]
    return Block(np.asarray(decisions), counts.get("on_time", 0), counts.get("missed", 0), result)


def sim_block(
    extra: Sequence[str], folder: Path, seconds: float, warm_up_s: float, realtime: bool = False
) -> Block:
    """A run of :func:`sim_command`, read (:func:`read_block`)."""
    started_ns = time.monotonic_ns()
    done = subprocess.run(sim_command(extra, folder, seconds, realtime), capture_output=True,
                          text=True)  # fmt: skip
    if done.returncode != 0:
        raise SystemExit(f"udan-edge exited {done.returncode}: {done.stderr[-500:]}")
    return read_block(folder, started_ns, warm_up_s)


def interleave(
    arms: dict[str, Callable[[Path], Block]], pairs: int, folder: Path
) -> dict[str, list[Block]]:
    """``pairs`` rounds of every arm in turn (A, B, A, B, ...), each in a folder of its own."""
    out: dict[str, list[Block]] = {arm: [] for arm in arms}
    for i in range(pairs):
        for arm, run in arms.items():
            block = folder / f"{arm}{i}"
            block.mkdir()
            out[arm].append(run(block))
            print(f"{arm} block {i + 1}/{pairs} done", file=sys.stderr)
    return out


def p99_ms(samples: np.ndarray) -> float:
    return float(np.percentile(samples, 99)) / 1e6


def p99_ratio(a: list[Block], b: list[Block], seed: int = 0) -> tuple[float, float, float]:
    """p99(B) / p99(A) over every step of each arm, and its 95 % CI from resampling the pairs
    of blocks."""
    pool_a = np.concatenate([x.decisions_ns for x in a])
    pool_b = np.concatenate([x.decisions_ns for x in b])
    ratio = p99_ms(pool_b) / p99_ms(pool_a)
    rng = np.random.default_rng(seed)
    ratios = []
    for _ in range(BOOTSTRAP):
        pick = rng.integers(0, len(a), len(a))
        ratios.append(
            p99_ms(np.concatenate([b[i].decisions_ns for i in pick]))
            / p99_ms(np.concatenate([a[i].decisions_ns for i in pick]))
        )
    low, high = np.percentile(ratios, [2.5, 97.5])
    return ratio, float(low), float(high)
