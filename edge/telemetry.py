"""What the runtime measured: spans per frame and per step, counts, a live line, a report.

Spans of the timing model (docs/timing.md), in the edge's monotonic clock (the cars' receive times
come back converted to it, and on one machine every process shares it):

- ``frame_age``: camera capture -> the frame handed over by the camera source (exposure,
  transfer, the driver's queue; 0 where a source knows no better than the arrival);
- ``frame_to_state``: camera capture -> cars' cells known (vision + fleet update);
- ``state_to_commands``: cells known -> every command of the step ready (masking, grouping,
  inference, safety);
- ``commands_to_received``: decision -> the last car of the step received its command (from
  the acks' receive times); ``decision_to_acked`` is the same until the last ack is back;
- ``frame_to_received``: capture of the frame a step decided on -> the last car received its
  command: the whole loop from the camera's exposure to the wheels.

The runtime runs for hours, so totals are fixed-size log histograms (0.9 % bin width: a
percentile is the upper edge of its bin, at most 0.09 ms above the true value at 10 ms), not
growing lists; the live line uses the last few hundred samples. Every record also goes,
one JSON object per line, to the telemetry file when one is given.
"""

from __future__ import annotations

import bisect
import json
import os
import sys
import time
from collections import Counter, deque
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import numpy as np

SPANS = (
    "frame_age",
    "frame_to_state",
    "state_to_commands",
    "commands_to_received",
    "decision_to_acked",
    "frame_to_received",
)
_LOG_MIN_NS, BINS_PER_DECADE, _DECADES = 1_000, 256, 8  # 1 us .. 100 s
BIN_RATIO = 10 ** (1 / BINS_PER_DECADE)
"""Upper over lower edge of every histogram bin (1.009)."""
DEADLINE_NS = 10_000_000
"""The dispatch deadline: every car has its command within 10 ms of the decision."""
BUCKETS_NS = (
    250_000, 500_000, 1_000_000, 2_000_000, 3_000_000, 5_000_000, 7_500_000, DEADLINE_NS,
    15_000_000, 25_000_000, 50_000_000, 100_000_000, 250_000_000, 1_000_000_000,
)  # fmt: skip
"""Upper edges of the cumulative buckets every span also keeps (Prometheus ``le``, for
``/metrics``): the deadline is one, so "within the deadline" is a bucket, not an estimate."""


class Histogram:
    """Log-binned durations (ns), constant memory; percentiles to about one bin width. Also
    counts in :data:`BUCKETS_NS` and sums, as a Prometheus histogram does."""

    def __init__(self) -> None:
        self.counts = np.zeros(BINS_PER_DECADE * _DECADES + 1, np.int64)
        self.n = 0
        self.max_ns = 0
        self.sum_ns = 0
        self.in_bucket = [0] * (len(BUCKETS_NS) + 1)  # the last: above every edge

    def add(self, ns: int) -> None:
        """Count one duration."""
        ratio = max(ns, _LOG_MIN_NS) / _LOG_MIN_NS
        b = min(int(np.log10(ratio) * BINS_PER_DECADE), len(self.counts) - 1)
        self.counts[b] += 1
        self.n += 1
        self.max_ns = max(self.max_ns, ns)
        self.sum_ns += ns
        self.in_bucket[bisect.bisect_left(BUCKETS_NS, ns)] += 1

    def cumulative(self) -> dict[str, Any]:
        """Counts at or below each of :data:`BUCKETS_NS` (and in all), and the sum in seconds."""
        running, at_most = 0, []
        for count in self.in_bucket:
            running += count
            at_most.append(running)
        return {"le_ns": BUCKETS_NS, "at_most": at_most, "sum_s": self.sum_ns / 1e9}

    def edges_ms(self) -> np.ndarray:
        """Lower edge of every bin, in milliseconds."""
        return _LOG_MIN_NS * 10 ** (np.arange(len(self.counts)) / BINS_PER_DECADE) / 1e6

    def percentile(self, q: float) -> float | None:
        """The q-th percentile in milliseconds (upper edge of its bin, capped at the max)."""
        if self.n == 0:
            return None
        b = int(np.searchsorted(np.cumsum(self.counts), q / 100 * self.n))
        upper = _LOG_MIN_NS * 10 ** ((b + 1) / BINS_PER_DECADE) / 1e6
        return round(min(upper, self.max_ns / 1e6), 4)

    def summary(self) -> dict[str, Any]:
        """Count, p50/p90/p99 and max in ms, and the non-empty bins (for plots)."""
        nz = np.flatnonzero(self.counts)
        return {
            "count": self.n,
            "p50_ms": self.percentile(50),
            "p90_ms": self.percentile(90),
            "p99_ms": self.percentile(99),
            "max_ms": round(self.max_ns / 1e6, 4) if self.n else None,
            "bins_ms": [round(float(v), 5) for v in self.edges_ms()[nz]],
            "bin_counts": self.counts[nz].tolist(),
        }


def resident_mb() -> float:
    """This process's resident memory now (Linux /proc; 0 where unavailable)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return 0.0
    return round(pages * os.sysconf("SC_PAGE_SIZE") / 2**20, 1)


MEMORY_PERIOD_S = 10.0
WARM_UP_S = 60.0


class Telemetry:
    """Collects frames and steps; writes JSON lines; prints the live line; builds the report."""

    def __init__(
        self,
        jsonl: str | Path | None = None,
        *,
        live: bool = True,
        stream: IO[str] | None = None,
        live_period_s: float = 1.0,
        tap: Callable[[dict[str, Any]], None] | None = None,
    ) -> None:
        """``tap`` is given every record as it is written (the flight recorder)."""
        self.spans = {name: Histogram() for name in SPANS}
        self.vision = Histogram()
        """Time the vision spent on each frame (in the perception process)."""
        self.recent = {name: deque(maxlen=400) for name in SPANS}
        self.counts: Counter[str] = Counter()
        self.per_car: dict[int, Counter[str]] = {}
        self.episodes: list[dict[str, Any]] = []
        self.started_ns = time.monotonic_ns()
        self.memory_start_mb = resident_mb()
        self.memory: list[tuple[float, float]] = []  # (seconds since start, MB) every 10 s
        self.cars = 0
        self.motion = {"offcentre_mm": 0.0, "heading_deg": 0.0, "seen_offcentre_mm": 0.0}
        """The largest off-centre distance and heading error of a car a step decided on, and
        the largest one the camera showed before a re-centring."""
        self._file = open(jsonl, "w", encoding="utf-8") if jsonl else None  # noqa: SIM115
        self._live = live
        self._stream = stream or sys.stdout
        self._tty = self._stream.isatty()
        self._period_ns = int(live_period_s * 1e9)
        self._next_live_ns = self.started_ns + self._period_ns
        self._steps_at_live = 0
        self._tap = tap

    def _span(self, name: str, ns: int | None) -> None:
        if ns is not None and ns >= 0:
            self.spans[name].add(ns)
            self.recent[name].append(ns)

    def _write(self, record: dict[str, Any]) -> None:
        if self._tap is not None:
            self._tap(record)
        if self._file is not None:
            self._file.write(json.dumps(record, separators=(",", ":")) + "\n")

    def frame(
        self,
        index: int,
        captured_ns: int,
        state_ns: int,
        seen: int,
        dropped: int,
        uncertain: int = 0,
        vision_ns: int | None = None,
        arrived_ns: int | None = None,
    ) -> None:
        """A frame was turned into cells (``state_ns``: when they were known); ``seen`` car
        markers on the grid, ``uncertain`` of them too near a border to place; it reached the
        edge's camera source at ``arrived_ns`` (None: at capture)."""
        self.counts["frames"] += 1
        self.counts["frames_dropped"] = dropped
        self.counts["sightings_found"] += seen - uncertain
        self.counts["sightings_uncertain"] += uncertain
        age = None if arrived_ns is None else arrived_ns - captured_ns
        self._span("frame_age", age)
        self._span("frame_to_state", state_ns - captured_ns)
        if vision_ns is not None:
            self.vision.add(vision_ns)
        self._write(
            {
                "kind": "frame",
                "index": index,
                "t_ns": captured_ns,
                "age_ns": age,
                "frame_to_state_ns": state_ns - captured_ns,
                "seen": seen,
                "uncertain": uncertain,
                "vision_ns": vision_ns,
            }
        )

    def step(self, record: dict[str, Any]) -> None:
        """One decision step: spans and counts from the runtime and the dispatcher."""
        self.counts["steps"] += 1
        self.cars = record["cars"]
        for key in (
            "on_time", "retried", "missed", "not_ready", "slow_sends", "late_sends",
            "late_executions", "blocked", "stopped", "uncertain", "uncalibrated",
        ):  # fmt: skip
            self.counts[key] += record.get(key, 0)
        self._outcomes(record)
        self._worst(record.get("offsets", {}), "offcentre_mm", "heading_deg")
        for car, sends in record.get("sends", {}).items():
            if sends:
                self.per_car[int(car)]["sent"] += 1
        for car in record.get("late_cars", ()):
            self.per_car[int(car)]["late"] += 1
        for name in SPANS[2:]:
            self._span(name, record.get(f"{name}_ns"))
        self._write({"kind": "step", **record})
        now_ns = record.get("t_ns", time.monotonic_ns())
        self._maybe_sample_memory(now_ns)
        self._maybe_live(now_ns)

    def recentre(self, record: dict[str, Any]) -> None:
        """A re-centring round (cars sent back to their cells' centres before a step): its
        commands count like a step's, and each car re-centred."""
        self.counts["recentre_rounds"] += 1
        self.counts["recentred"] += len(record["cars"])
        for key in ("on_time", "missed", "not_ready", "late_sends", "late_executions"):
            self.counts[key] += record.get(key, 0)
        self._outcomes(record)
        for car in record["cars"]:
            self.per_car.setdefault(int(car), Counter())["recentred"] += 1
        self._worst(record["offsets"], "seen_offcentre_mm")
        self._write({"kind": "recentre", **record})

    def _outcomes(self, record: dict[str, Any]) -> None:
        for car, outcome in record.get("outcomes", {}).items():
            self.per_car.setdefault(int(car), Counter())[outcome] += 1

    def _worst(self, offsets: dict[str, list[float]], distance: str, heading: str = "") -> None:
        """Keep the largest of ``offsets`` (car -> [mm off centre, degrees off facing up])."""
        for mm, degrees in offsets.values():
            self.motion[distance] = max(self.motion[distance], mm)
            if heading:
                self.motion[heading] = max(self.motion[heading], abs(degrees))
        if not heading:
            return
        self.motion["seen_offcentre_mm"] = max(
            self.motion["seen_offcentre_mm"], self.motion[distance]
        )

    def _maybe_sample_memory(self, now_ns: int) -> None:
        """Resident memory every ``MEMORY_PERIOD_S``: growth in a run of hours shows here."""
        elapsed_s = (now_ns - self.started_ns) / 1e9
        if elapsed_s >= MEMORY_PERIOD_S * (len(self.memory) + 1):
            self.memory.append((round(elapsed_s, 1), resident_mb()))
            self._write({"kind": "memory", "t_ns": now_ns, "resident_mb": self.memory[-1][1]})

    def event(self, kind: str, **fields: Any) -> None:
        """A fleet or camera event (join, leave, stall, estop, episode)."""
        self.counts[kind] += 1
        self._write({"kind": kind, "t_ns": time.monotonic_ns(), **fields})

    def episode(self, record: dict[str, Any]) -> None:
        """An episode finished (HIL/--sim): its returns per car."""
        self.episodes.append(record)
        self._write({"kind": "episode", **record})
        if self._file is not None:
            self._file.flush()

    def _p99(self, name: str) -> str:
        values = self.recent[name]
        return f"{np.percentile(values, 99) / 1e6:.2f}" if values else "-"

    def live_line(self, now_ns: int) -> str:
        """cars, steps/s since the last line, p99 of each span (recent), misses so far."""
        elapsed = max(now_ns - (self._next_live_ns - self._period_ns), 1)
        rate = (self.counts["steps"] - self._steps_at_live) * 1e9 / elapsed
        return (
            f"cars {self.cars} | steps {self.counts['steps']} ({rate:.1f}/s) | p99 ms: "
            f"frame→state {self._p99('frame_to_state')}, "
            f"state→cmds {self._p99('state_to_commands')}, "
            f"cmds→received {self._p99('commands_to_received')} | "
            f"on time {self.counts['on_time']}, missed {self.counts['missed']}, "
            f"late {self.counts['late_sends']} | dropped frames {self.counts['frames_dropped']}"
        )

    def _maybe_live(self, now_ns: int) -> None:
        """The live line, and the telemetry file flushed, once a period (someone may be
        following the file: ``udan-hil run`` shows its progress from it)."""
        if now_ns < self._next_live_ns:
            return
        if self._live:
            line = self.live_line(now_ns)
            self._stream.write(("\r\x1b[K" + line) if self._tty else line + "\n")
            self._stream.flush()
        if self._file is not None:
            self._file.flush()
        self._next_live_ns = now_ns + self._period_ns
        self._steps_at_live = self.counts["steps"]

    def report(self) -> dict[str, Any]:
        """Everything at exit: counts, span summaries, per-car outcomes, episodes, memory."""
        duration = (time.monotonic_ns() - self.started_ns) / 1e9
        commands = self.counts["on_time"] + self.counts["missed"]
        return {
            "duration_s": round(duration, 2),
            "counts": dict(self.counts),
            "on_time_share": round(self.counts["on_time"] / commands, 6) if commands else None,
            "steps_per_s": round(self.counts["steps"] / duration, 2) if duration else None,
            "spans": {name: h.summary() for name, h in self.spans.items()},
            "vision": self.vision.summary(),
            "per_car": {str(c): dict(v) for c, v in sorted(self.per_car.items())},
            "episodes": self.episodes,
            "memory_mb": self.memory_summary(),
            "motion": dict(self.motion),
        }

    def totals(self) -> dict[str, Any]:
        """The running totals, for the live view and ``/metrics``: counts, per-car outcomes
        (``sent``, ``on_time``, ``missed``, ``not_ready``, ``late``), and each span's and the
        vision's cumulative buckets. What the report will say, so far."""
        return {
            "counts": dict(self.counts),
            "per_car": {str(c): dict(v) for c, v in self.per_car.items()},
            "histograms": {
                **{name: h.cumulative() for name, h in self.spans.items()},
                "vision": self.vision.cumulative(),
            },
            "episodes": len(self.episodes),
        }

    def memory_summary(self) -> dict[str, float | None]:
        """Resident MB at start, after the first minute (models loaded, buffers grown: the
        baseline for growth), at its peak and now."""
        warm = next((mb for t, mb in self.memory if t >= WARM_UP_S), None)
        end = resident_mb()
        return {
            "start": self.memory_start_mb,
            "after_1min": warm,
            "peak": max([end, *(mb for _, mb in self.memory)]),
            "end": end,
        }

    def final_line(self) -> str:
        """One line for the end of a run: steps, episodes and their mean score, deadlines."""
        counts, scores = self.counts, [e["score"] for e in self.episodes if e["score"] is not None]
        commands = counts["on_time"] + counts["missed"]
        share = f"{100 * counts['on_time'] / commands:.2f} %" if commands else "-"
        episodes = (
            f"{len(scores)} episodes, mean score {sum(scores) / len(scores):.2f}"
            if scores
            else "no complete episode"
        )
        return (
            f"{counts['steps']} steps, {episodes}; commands on time {share} "
            f"({counts['missed']} missed, {counts['late_sends']} sent late, "
            f"{counts['late_executions']} executed late); memory {self.memory_start_mb} -> "
            f"{resident_mb()} MB"
        )

    def close(self) -> None:
        """End the live line and close the telemetry file."""
        if self._live and self._tty:
            self._stream.write("\n")
        if self._file is not None:
            self._file.close()
            self._file = None
