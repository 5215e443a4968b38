"""The HIL report: ``summary.json``, PNGs (with matplotlib) and ``report.html``, from what the
edge, the cars and the world counted.

- ``latency.png``: histograms of the timing model's spans (edge telemetry);
- ``misses.png``: commands per car that missed their deadline (and were retried);
- ``scores.png``: the paper-style table (cars x obstacles, average agent score) through the full
  loop beside the pure simulation of the same policy on the same layouts, and their gap;
- ``motion.png``: each car's distance from its cell's centre and heading error at every step,
  as the camera saw them, with the settling tolerance, and the re-centring rounds;
- ``report.html``: all of it on one page, one file readable offline (the PNGs inside it as data
  URIs, no script, nothing fetched), to mail or attach to a ticket.

The motion figures (``motion`` in the summary, the issue's "Done when" in docs/motion.md) come
from the edge's telemetry file: each step's and re-centring round's record says how far off
each car was and which cars were commanded, so drift over time (first minute against last),
re-centring per car per minute and the longest a car went uncommanded within an episode are
read from it.
"""

from __future__ import annotations

import argparse
import base64
import html
import importlib.util
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from udan.edge.telemetry import BIN_RATIO

SPAN_TITLES = {
    "frame_age": "frame age on arrival",
    "frame_to_state": "frame → state",
    "state_to_commands": "state → commands",
    "commands_to_received": "commands → received by car",
    "decision_to_acked": "decision → all acked",
    "frame_to_received": "frame → all commands received",
}


def score_table(
    episodes: list[dict[str, Any]], sim: list[float]
) -> tuple[list[dict[str, Any]], dict[str, float | None]]:
    """Per (cars, obstacles) cell: episodes, HIL mean, sim mean; and the overall means and gap.

    The gap is (sim - HIL) / sim of the means over every episode both played."""
    cells: dict[tuple[int, int], list[tuple[float, float]]] = defaultdict(list)
    for episode, sim_score in zip(episodes, sim, strict=True):
        if episode.get("score") is not None:
            cells[(episode["agents"], episode["obstacles"])].append((episode["score"], sim_score))
    rows = []
    for (agents, obstacles), pairs in sorted(cells.items()):
        hil, ref = np.array(pairs).T
        rows.append(
            {
                "agents": agents,
                "obstacles": obstacles,
                "episodes": len(pairs),
                "hil": round(float(hil.mean()), 3),
                "sim": round(float(ref.mean()), 3),
            }
        )
    pairs = [p for v in cells.values() for p in v]
    if not pairs:
        return rows, {"hil": None, "sim": None, "gap": None}
    hil, ref = np.array(pairs).T
    gap = (ref.mean() - hil.mean()) / ref.mean() if ref.mean() else None
    return rows, {
        "hil": round(float(hil.mean()), 3),
        "sim": round(float(ref.mean()), 3),
        "gap": None if gap is None else round(float(gap), 5),
        "episodes": len(pairs),
        "identical_episodes": int(np.sum(np.isclose(hil, ref))),
    }


def _car_totals(cars: dict[str, dict[str, Any]]) -> dict[str, int]:
    """Counters summed over cars (rejections by reason flattened as rejected_REASON)."""
    totals: dict[str, int] = defaultdict(int)
    for counters in cars.values():
        for key, value in counters.items():
            if isinstance(value, bool) or value is None:
                continue
            if isinstance(value, int | float):
                totals[key] += int(value)
            elif isinstance(value, dict):
                for sub, v in value.items():
                    if isinstance(v, int | float) and not isinstance(v, bool):
                        totals[f"{key}_{sub}"] += int(v)
    return dict(totals)


MINUTE_NS = 60_000_000_000


def _records(path: Path) -> list[dict[str, Any]]:
    if not path.is_file():
        return []
    with path.open(encoding="utf-8") as lines:
        return [json.loads(line) for line in lines if line.strip()]


def motion_summary(records: list[dict[str, Any]], world: dict[str, Any]) -> dict[str, Any]:
    """How far the cars strayed and what it took to keep them on their cells (see the module
    docstring); ``world`` is the world's state at the end (the truth)."""
    steps = [r for r in records if r["kind"] == "step"]
    rounds = [r for r in records if r["kind"] == "recentre"]
    if not steps:
        return {}
    t0 = steps[0]["t_ns"]
    minutes: dict[int, list[float]] = defaultdict(list)
    headings: dict[int, list[float]] = defaultdict(list)
    per_car: dict[str, dict[int, list[float]]] = defaultdict(lambda: defaultdict(lambda: [0, 0]))
    for r in steps:
        minute = (r["t_ns"] - t0) // MINUTE_NS
        for car, (mm, degrees) in r["offsets"].items():
            minutes[minute].append(mm)
            headings[minute].append(abs(degrees))
            worst = per_car[car][minute]
            worst[0], worst[1] = max(worst[0], mm), max(worst[1], abs(degrees))
    by_minute = [
        {
            "minute": m,
            "offcentre_p50_mm": round(float(np.median(minutes[m])), 1),
            "offcentre_max_mm": max(minutes[m]),
            "heading_max_deg": max(headings[m]),
        }
        for m in sorted(minutes)
    ]
    span_min = max((records[-1]["t_ns"] - t0) / MINUTE_NS, 1e-9)
    recentred: dict[str, int] = defaultdict(int)
    for r in rounds:
        for car in r["cars"]:
            recentred[str(car)] += 1
    cars = sorted({c for r in steps for c in r["outcomes"]}, key=int)
    seen = [mm for r in rounds for mm, _ in r["offsets"].values()]
    true = [
        off for minutes_of_car in world.get("settled", {}).values() for off, _ in minutes_of_car
    ]
    return {
        "steps_measured": len(steps),
        "offcentre_max_mm_at_decisions": max((m["offcentre_max_mm"] for m in by_minute), default=0),
        "heading_max_deg_at_decisions": max((m["heading_max_deg"] for m in by_minute), default=0),
        "offcentre_max_mm_seen": max([*seen, *(m["offcentre_max_mm"] for m in by_minute)]),
        "true_offcentre_max_mm": round(1000 * max(true), 1) if true else None,
        "offcentre_by_minute": by_minute,
        "per_car_by_minute": {
            car: [
                {"minute": m, "offcentre_max_mm": w[0], "heading_max_deg": w[1]}
                for m, w in sorted(per_car[car].items())
            ]
            for car in sorted(per_car, key=int)
        },
        "recentre_rounds": len(rounds),
        "recentred_per_car_per_min": {c: round(recentred[c] / span_min, 2) for c in cars},
        "guard_stops": sum(len(r["cars"]) for r in records if r["kind"] == "guard_stop"),
        "longest_uncommanded_s": _longest_uncommanded(records),
    }


def _longest_uncommanded(records: list[dict[str, Any]]) -> dict[str, float]:
    """Per car, the longest time between two commands it received within one episode (steps,
    re-centring rounds; the pause between episodes is not counted)."""
    longest: dict[str, float] = defaultdict(float)
    last: dict[str, int] = {}
    for r in records:
        if r["kind"] == "episode":
            last.clear()
        for car, outcome in r.get("outcomes", {}).items():
            if outcome != "on_time":
                continue
            if car in last:
                longest[car] = max(longest[car], (r["t_ns"] - last[car]) / 1e9)
            last[car] = r["t_ns"]
    return {c: round(v, 3) for c, v in sorted(longest.items(), key=lambda kv: int(kv[0]))}


def _plot_motion(records: list[dict[str, Any]], tolerance_mm: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [r for r in records if r["kind"] == "step"]
    t0 = steps[0]["t_ns"]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    for car in sorted({c for r in steps for c in r["offsets"]}, key=int):
        t = [(r["t_ns"] - t0) / 1e9 for r in steps if car in r["offsets"]]
        top.plot(t, [r["offsets"][car][0] for r in steps if car in r["offsets"]], ".", ms=2,
                 label=f"car {car}")  # fmt: skip
        bottom.plot(t, [r["offsets"][car][1] for r in steps if car in r["offsets"]], ".", ms=2)
    for r in records:
        if r["kind"] == "recentre":
            top.axvline((r["t_ns"] - t0) / 1e9, color="0.85", lw=0.5, zorder=0)
    top.axhline(tolerance_mm, color="tab:red", lw=1, label=f"tolerance {tolerance_mm:g} mm")
    top.set_ylabel("off centre at a step (mm)")
    bottom.set_ylabel("heading at a step (deg)")
    bottom.set_xlabel("s (grey: re-centring rounds)")
    top.legend(fontsize=7, markerscale=4, ncol=3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_latency(edge: dict[str, Any], path: Path) -> None:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spans = edge["spans"]
    fig, axes = plt.subplots(1, len(SPAN_TITLES), figsize=(4.2 * len(SPAN_TITLES), 3.2))
    for ax, (name, title) in zip(axes, SPAN_TITLES.items(), strict=True):
        s = spans.get(name, {})
        if s.get("count"):
            ax.bar(s["bins_ms"], s["bin_counts"], width=np.array(s["bins_ms"]) * (BIN_RATIO - 1))
            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            ax.axvline(s["p99_ms"], color="tab:red", lw=1, label=f"p99 {s['p99_ms']:.2f} ms")
            ax.legend(fontsize=8)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("ms")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_misses(edge: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    per_car = edge.get("per_car", {})
    cars = sorted(per_car, key=int)
    fig, ax = plt.subplots(figsize=(5, 3))
    on_time = [per_car[c].get("on_time", 0) for c in cars]
    missed = [per_car[c].get("missed", 0) for c in cars]
    x = np.arange(len(cars))
    ax.bar(x - 0.2, missed, 0.4, label="missed", color="tab:red")
    ax2 = ax.twinx()
    ax2.bar(x + 0.2, on_time, 0.4, label="on time", color="tab:green", alpha=0.5)
    ax.set_xticks(x, [f"car {c}" for c in cars])
    ax.set_ylabel("commands missed")
    ax2.set_ylabel("commands on time")
    ax.set_title("dispatch deadline per car")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_scores(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    agents = sorted({r["agents"] for r in rows})
    obstacles = sorted({r["obstacles"] for r in rows})
    grids = {k: np.full((len(obstacles), len(agents)), np.nan) for k in ("hil", "sim")}
    for r in rows:
        for k in grids:
            grids[k][obstacles.index(r["obstacles"]), agents.index(r["agents"])] = r[k]
    gap = grids["sim"] - grids["hil"]
    fig, axes = plt.subplots(1, 3, figsize=(12, 0.45 * len(obstacles) + 2.2))
    panels = (
        ("full loop (HIL)", grids["hil"]),
        ("pure simulation", grids["sim"]),
        ("sim − HIL", gap),
    )
    for ax, (title, grid) in zip(axes, panels, strict=True):
        ax.imshow(grid, cmap="viridis" if "−" not in title else "coolwarm", aspect="auto")
        for (i, j), v in np.ndenumerate(grid):
            if not np.isnan(v):
                ax.text(j, i, f"{v:.1f}", ha="center", va="center", fontsize=7, color="w")
        ax.set_xticks(range(len(agents)), agents)
        ax.set_yticks(range(len(obstacles)), obstacles)
        ax.set_xlabel("cars")
        ax.set_ylabel("obstacles")
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def can_plot() -> bool:
    """The PNGs need matplotlib (the ``hil`` and ``train`` extras); a base install, as on the
    edge computer, still writes ``summary.json``."""
    return importlib.util.find_spec("matplotlib") is not None


def write_report(
    args: argparse.Namespace, result: dict[str, Any], sim: list[float], folder: Path
) -> dict[str, Any]:
    """Write summary.json and, where :func:`can_plot`, the PNGs into ``folder``; returns the
    summary."""
    edge, world = result["edge"], result["world"]
    rows, scores = score_table(edge["episodes"], sim)
    records = _records(folder / "telemetry.jsonl")
    motion = motion_summary(records, world.get("state", {}))
    cars = _car_totals(world.get("cars", {}))
    counts = edge["counts"]
    headline = {
        "episodes": len(edge["episodes"]),
        "episodes_planned": result.get("planned"),
        "interrupted": result.get("interrupted"),
        "score_hil": scores["hil"],
        "score_sim": scores["sim"],
        "sim_to_hil_gap": scores["gap"],
        "steps": counts.get("steps", 0),
        "commands_on_time_share": edge.get("on_time_share"),
        "commands_missed": counts.get("missed", 0),
        "slow_sends": counts.get("slow_sends", 0),
        "late_sends": counts.get("late_sends", 0),
        "late_executions": counts.get("late_executions", 0),
        "collisions": world.get("world", {}).get("collisions"),
        "motion_error": args.motion_error,
        **{
            key: motion.get(key)
            for key in (
                "offcentre_max_mm_at_decisions",
                "heading_max_deg_at_decisions",
                "offcentre_max_mm_seen",
                "true_offcentre_max_mm",
                "recentred_per_car_per_min",
                "longest_uncommanded_s",
            )
        },
        "p99_ms": {name: edge["spans"][name]["p99_ms"] for name in SPAN_TITLES},
        "edge_memory_mb": edge.get("memory_mb"),
        "edge_scheduler": edge.get("scheduler"),
        "perception_scheduler": edge.get("perception_scheduler"),
        "cars_scheduler": world.get("scheduler"),
        "esp_scheduler": world.get("esp_scheduler"),
        "camera_scheduler": world.get("camera_scheduler"),
        "exits": result["exits"],
    }
    if "sightings" in result:
        headline["wrong_cells"] = result["sightings"].get("wrong")
    summary = {
        "headline": headline,
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
        "scores": {"overall": scores, "cells": rows},
        "edge": {k: v for k, v in edge.items() if k != "episodes"},
        "episodes": [{**e, "sim_score": s} for e, s in zip(edge["episodes"], sim, strict=True)],
        "cars": cars,
        "world": world,
        "events": result["events"],
        "motion": motion,
        **({"sightings": result["sightings"]} if "sightings" in result else {}),
    }
    (folder / "summary.json").write_text(json.dumps(summary, indent=1), encoding="utf-8")
    pictures = []
    if can_plot():
        _plot_latency(edge, folder / "latency.png")
        _plot_misses(edge, folder / "misses.png")
        pictures = ["latency.png", "misses.png"]
        if rows:
            _plot_scores(rows, folder / "scores.png")
            pictures.append("scores.png")
        if motion:
            _plot_motion(records, args.settle_mm, folder / "motion.png")
            pictures.append("motion.png")
    (folder / "report.html").write_text(
        html_report(summary, {name: (folder / name).read_bytes() for name in pictures}),
        encoding="utf-8",
    )
    return summary


PICTURE_TITLES = {
    "scores.png": "Scores: the full loop beside the pure simulation",
    "latency.png": "Latency of each span",
    "misses.png": "Dispatch deadline per car",
    "motion.png": "Each car's distance from its cell's centre and heading error, at every step",
}


def _table(rows: list[list[Any]], head: list[str] | None = None) -> str:
    def cell(tag: str, value: Any) -> str:
        text = "-" if value is None else value
        return f"<{tag}>{html.escape(str(text))}</{tag}>"

    out = ["<table>"]
    if head:
        out.append("<tr>" + "".join(cell("th", h) for h in head) + "</tr>")
    out += ["<tr>" + "".join(cell("td", v) for v in row) + "</tr>" for row in rows]
    return "\n".join([*out, "</table>"])


def html_report(summary: dict[str, Any], pictures: dict[str, bytes]) -> str:
    """The whole report as one HTML page: the headline, the score table, what each car
    counted, the faults applied, and ``pictures`` (PNG bytes by file name) inlined."""
    head = summary["headline"]
    headline = [[k.replace("_", " "), v] for k, v in head.items() if not isinstance(v, dict)]
    headline += [[f"p99 {k.replace('_', ' ')} (ms)", v] for k, v in head["p99_ms"].items()]
    headline += [[f"exit of {k}", v] for k, v in head["exits"].items()]
    cells = summary["scores"]["cells"]
    score_rows = [[r["agents"], r["obstacles"], r["episodes"], r["hil"], r["sim"],
                   round(r["sim"] - r["hil"], 3)] for r in cells]  # fmt: skip
    per_car = summary["edge"].get("per_car", {})
    kinds = sorted({k for counts in per_car.values() for k in counts})
    car_rows = [[car, *(per_car[car].get(k, 0) for k in kinds)] for car in per_car]
    events = [[e.get("at_s"), e["kind"], e.get("car")] for e in summary["events"]]
    config = [[k, v] for k, v in summary["config"].items()]
    figures = "\n".join(
        f'<figure><img alt="{html.escape(PICTURE_TITLES[name])}" '
        f'src="data:image/png;base64,{base64.b64encode(data).decode()}">'
        f"<figcaption>{html.escape(PICTURE_TITLES[name])}</figcaption></figure>"
        for name, data in sorted(pictures.items(), key=lambda kv: list(PICTURE_TITLES).index(kv[0]))
    )
    if not pictures:
        figures = "<p>No plots: matplotlib is missing (pip install 'udan-edge[hil]').</p>"
    stopped = head.get("interrupted")
    banner = (
        f"<p class=warn>Stopped by {html.escape(stopped)}: this report covers the "
        f"{head['episodes']} episodes completed.</p>"
        if stopped
        else ""
    )
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>udan-hil run report</title>
<style>
body {{ font: 14px system-ui, sans-serif; margin: 2em; color: #222; }}
table {{ border-collapse: collapse; margin-bottom: 1.5em; }}
td, th {{ border-bottom: 1px solid #ddd; padding: 2px 10px; text-align: left; }}
img {{ max-width: 100%; }} .warn {{ color: #b00; font-weight: bold; }}
</style></head><body>
<h1>udan-hil run</h1>
{banner}
<h2>Headline</h2>
{_table(headline)}
<h2>Scores by cell (average agent return)</h2>
{_table(score_rows, ["cars", "obstacles", "episodes", "full loop", "simulation", "sim − loop"])}
{figures}
<h2>Commands per car (the edge's count)</h2>
{_table(car_rows, ["car", *kinds])}
<h2>Faults applied</h2>
{_table(events, ["at (s)", "kind", "car"]) if events else "<p>none</p>"}
<h2>Configuration</h2>
{_table(config)}
</body></html>
"""
