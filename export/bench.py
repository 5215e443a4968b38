"""Latency of an exported policy in onnxruntime and of the same model in torch eager, one run.

Two figures per fleet size N, both on one thread:

- ``call``: one inference of the graph with groups in force, as :class:`OnnxPolicy` makes it
  at a step between group formations (:class:`udan.export.runtime.BoundGraph`: observations copied
  into bound buffers; torch: the same computation, :func:`udan.export.verify.torch_step`). The
  agents with the model's top 1/k leader scores lead, so groups cover the fleet whatever the
  threshold of a barely trained model would give. The targets are on this figure.
- ``step``: a whole decision step as the edge takes it, :class:`udan.export.runtime.OnnxPolicy.act`
  vs :meth:`udan.learner.Actor.act`, over consecutive steps with groups formed every T steps
  (numpy grouping included, and the second graph call at formation steps).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from udan.envs.grouping import form_groups, neighbour_table
from udan.export.runtime import BoundGraph, OnnxPolicy, PolicyGraph, no_neighbours, round_inputs
from udan.export.verify import torch_step
from udan.learner import Actor, MultiAgentQ

SIZES = (1, 5, 20, 64, 200, 1000)
TARGETS = {"n5_median_ms": 0.1, "n1000_p99_ms": 5.0}


def _scenario(n: int, obs_dim: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """N agents at the arena's density (5 on 9x9) on a square grid, random sparse views."""
    side = max(9, math.ceil(math.sqrt(n * 81 / 5)))
    cells = rng.choice(side * side, size=n, replace=False)
    return {
        "pos": np.stack([cells // side, cells % side], axis=1),
        "present": np.ones(n, bool),
        "obs": (rng.random((n, obs_dim)) < 0.15).astype(np.float32),
    }


def _timed(fn: Callable[[], object], repeats: int) -> dict[str, float]:
    fn()  # warm-up: first-call allocations are not what a running edge pays
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    ms = np.array(times) * 1e3
    return {"median": round(float(np.median(ms)), 4), "p99": round(float(np.quantile(ms, 0.99)), 4)}


def _pair(ort_fn: Callable[[], object], torch_fn: Callable[[], object], repeats: int) -> dict:
    onnx_ms, torch_ms = _timed(ort_fn, repeats), _timed(torch_fn, repeats)
    ratio = onnx_ms["median"] / torch_ms["median"]
    return {"onnxruntime": onnx_ms, "torch": torch_ms, "ratio": round(ratio, 3)}


def bench(
    path: str | Path,
    model: MultiAgentQ,
    sizes: Sequence[int] = SIZES,
    repeats: int = 200,
    seed: int = 0,
) -> dict:
    """Figures for every size as one JSON-ready dict (targets and whether they are met)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        rows = [_bench_size(Path(path), model, n, repeats, seed) for n in sizes]
    finally:
        torch.set_num_threads(threads)
    by_n = {row["agents"]: row for row in rows}
    met = {"onnxruntime_faster_than_torch": all(r["call_ms"]["ratio"] < 1 for r in rows)}
    if 5 in by_n:
        met["n5_median_ms"] = by_n[5]["call_ms"]["onnxruntime"]["median"] <= TARGETS["n5_median_ms"]
    if 1000 in by_n:
        met["n1000_p99_ms"] = by_n[1000]["call_ms"]["onnxruntime"]["p99"] <= TARGETS["n1000_p99_ms"]
    return {
        "model": {"path": str(path), "algo": model.spec.algo, "hidden": model.spec.hidden},
        "threads": 1,
        "versions": {"onnxruntime": ort.__version__, "torch": torch.__version__},
        "repeats": repeats,
        "targets": TARGETS,
        "met": met,
        "sizes": rows,
    }


def _bench_size(path: Path, model: MultiAgentQ, n: int, repeats: int, seed: int) -> dict:
    spec = model.spec
    rng = np.random.default_rng(seed)
    scene = _scenario(n, spec.obs_dim, rng)
    graph = PolicyGraph(path)
    feeds = {
        "obs": scene["obs"],
        "h": np.zeros((1, n, spec.hidden), np.float32),
        "c": np.zeros((1, n, spec.hidden), np.float32),
        "fresh": np.zeros(n, bool),
        "neighbours": neighbour_table(scene["pos"], scene["present"], spec.attention_neighbours),
    }
    groups = np.zeros((0, 0), np.int64)
    if spec.communicates:  # the model's top 1/k scores lead: the fleet is covered by groups
        logits = graph.run({**feeds, **round_inputs(groups)})["leader_logits"]
        threshold = np.quantile(logits, 1 - 1 / spec.group_size) if n > 1 else np.inf
        groups = form_groups(scene["pos"], scene["present"], logits, spec.group_size, threshold)
        feeds["neighbours"] = no_neighbours(n)  # what a step between formations passes
    feeds.update(round_inputs(groups))
    bound = BoundGraph(graph, feeds["h"].copy(), feeds["c"].copy())
    if spec.communicates:
        bound.bind_groups(groups)
    row = {
        "agents": n,
        "groups": len(groups),
        "rounds": len(feeds["round_groups"]),
        "call_ms": _pair(
            lambda: bound.run(scene["obs"]), lambda: torch_step(model, feeds, groups), repeats
        ),
    }
    policy, actor = OnnxPolicy(path), Actor(model, 1, n)
    policy.reset(n)
    args = (scene["obs"], scene["present"], scene["pos"], feeds["fresh"])
    row["step_ms"] = _pair(
        lambda: policy.act(*args), lambda: actor.act(*(a[None] for a in args)), repeats
    )
    return row
