"""Edge telemetry: constant-memory histograms that agree with exact percentiles, the report."""

from __future__ import annotations

import io
import json
import time

import numpy as np

from udan.edge.telemetry import BIN_RATIO, DEADLINE_NS, Histogram, Telemetry


def test_histogram_percentiles_within_a_bin_of_the_exact_ones() -> None:
    """A percentile is the upper edge of its bin: never below the exact one, and above it by
    less than one bin (0.9 %: 0.09 ms at 10 ms, where the loop's p99 targets are)."""
    rng = np.random.default_rng(0)
    for mean in (13.5, 15.9):  # ~1 ms and ~8 ms
        samples = (rng.lognormal(mean=mean, sigma=0.5, size=20_000)).astype(np.int64)
        hist = Histogram()
        for ns in samples:
            hist.add(int(ns))
        for q in (50, 90, 99):
            exact = np.percentile(samples, q) / 1e6
            assert -1e-3 < (hist.percentile(q) - exact) / exact < BIN_RATIO - 1 + 1e-3
    assert hist.summary()["max_ms"] == round(samples.max() / 1e6, 4)
    assert sum(hist.summary()["bin_counts"]) == len(samples)


def test_report_counts_spans_and_json_lines(tmp_path) -> None:
    stream = io.StringIO()
    tel = Telemetry(tmp_path / "t.jsonl", live=True, stream=stream, live_period_s=0.0)
    tel.frame(0, captured_ns=1_000_000, state_ns=4_000_000, seen=2, dropped=0)
    record = {
        "t_ns": time.monotonic_ns(), "cars": 2, "state_to_commands_ns": 300_000,
        "commands_to_received_ns": 2_000_000, "decision_to_acked_ns": 3_000_000,
        "on_time": 1, "missed": 1, "late_sends": 0, "outcomes": {"1": "on_time", "2": "missed"},
    }  # fmt: skip
    tel.step(record)
    tel.episode({"index": 0, "score": 40.0, "returns": {"1": 40.0}})
    report = tel.report()
    tel.close()
    assert report["counts"]["steps"] == 1 and report["counts"]["missed"] == 1
    assert report["on_time_share"] == 0.5
    assert report["per_car"] == {"1": {"on_time": 1}, "2": {"missed": 1}}
    assert report["spans"]["frame_to_state"]["count"] == 1
    assert abs(report["spans"]["state_to_commands"]["p50_ms"] - 0.3) < 0.02
    kinds = [json.loads(line)["kind"] for line in (tmp_path / "t.jsonl").read_text().splitlines()]
    assert kinds == ["frame", "step", "episode"]
    assert "cars 2" in stream.getvalue() and "missed 1" in stream.getvalue()
    assert "1 episodes, mean score 40.00" in tel.final_line()


def test_memory_is_sampled_every_ten_seconds_of_the_run(tmp_path) -> None:
    tel = Telemetry(tmp_path / "t.jsonl", live=False)
    for second in range(0, 75, 5):
        tel.step({"t_ns": tel.started_ns + second * 10**9, "cars": 1})
    memory = tel.report()["memory_mb"]
    tel.close()
    assert [t for t, _ in tel.memory] == [10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0]
    assert memory["after_1min"] == tel.memory[5][1] > 0
    assert memory["peak"] >= max(memory["end"], memory["after_1min"])
    lines = [json.loads(line) for line in (tmp_path / "t.jsonl").read_text().splitlines()]
    assert sum(line["kind"] == "memory" for line in lines) == 7


def test_buckets_count_at_or_below_each_edge_and_the_deadline_is_one() -> None:
    hist = Histogram()
    samples = [100_000, DEADLINE_NS, DEADLINE_NS + 1, 3_000_000, 2_000_000_000]
    for ns in samples:
        hist.add(ns)
    cumulative = hist.cumulative()
    edges = list(cumulative["le_ns"])
    assert DEADLINE_NS in edges
    for edge, count in zip(edges, cumulative["at_most"], strict=False):
        assert count == sum(ns <= edge for ns in samples)
    assert cumulative["at_most"][-1] == len(samples)  # +Inf
    assert cumulative["sum_s"] == sum(samples) / 1e9


def test_totals_are_what_the_report_says_so_far(tmp_path) -> None:
    tel = Telemetry(tmp_path / "t.jsonl", live=False)
    tel.frame(0, captured_ns=0, state_ns=2_000_000, seen=3, dropped=0, uncertain=1, vision_ns=10)
    record = {
        "t_ns": time.monotonic_ns(), "cars": 2, "state_to_commands_ns": 400_000,
        "on_time": 1, "missed": 1, "outcomes": {"1": "on_time", "2": "missed"},
        "sends": {"1": 1, "2": 0}, "late_cars": [2],
    }  # fmt: skip
    tel.step(record)
    totals, report = tel.totals(), tel.report()
    tel.close()
    assert totals["counts"] == report["counts"]
    assert totals["counts"]["sightings_found"] == 2 and totals["counts"]["sightings_uncertain"] == 1
    assert totals["per_car"] == report["per_car"]
    assert totals["per_car"] == {
        "1": {"on_time": 1, "sent": 1},
        "2": {"missed": 1, "late": 1},
    }
    decision = totals["histograms"]["state_to_commands"]
    assert decision["at_most"][-1] == report["spans"]["state_to_commands"]["count"] == 1
    assert totals["histograms"]["vision"]["at_most"][-1] == report["vision"]["count"] == 1
    json.dumps(totals)
