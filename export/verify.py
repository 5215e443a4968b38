"""Does an exported file compute what the checkpoint's torch model computes, at every size?

Three checks, run on every export and by ``udan-export verify``: the ONNX checker with full
shape inference, every dynamic axis symbolic in the saved file (a graph with the agent or group
count fixed would pass a parity test at that size only), and onnxruntime vs torch over several
consecutive steps of recurrent state at many fleet sizes, with random groupings that include
bridging and lone agents (the runtime zeroes a fresh slot's state before the graph, as
:class:`udan.export.runtime.OnnxPolicy` does).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import onnx
import torch

from udan.envs.grouping import neighbour_table
from udan.export.graph import AXES
from udan.export.runtime import PolicyGraph, forget, no_neighbours, round_inputs
from udan.learner import MultiAgentQ, merge_rounds

SIZES = (1, 2, 3, 5, 8, 20, 64, 1000)
TOLERANCE = 1e-4
"""Largest |ΔQ| (and |Δ| of recurrent state and leader logits) accepted between ORT and torch."""


@dataclass
class SizeResult:
    """Parity figures at one fleet size, over all steps."""

    agents: int
    steps: int
    groups: int
    rounds: int
    bridges: int
    lone: int
    max_dq: float
    max_dstate: float
    max_dlogits: float
    actions_equal: bool

    @property
    def ok(self) -> bool:
        worst = max(self.max_dq, self.max_dstate, self.max_dlogits)
        return self.actions_equal and worst <= TOLERANCE

    def line(self) -> str:
        return (
            f"N={self.agents:5d}  groups {self.groups:4d}  rounds {self.rounds:2d}  "
            f"bridges {self.bridges:4d}  lone {self.lone:4d}  max|ΔQ| {self.max_dq:.2e}  "
            f"max|Δh,c| {self.max_dstate:.2e}  max|Δleader| {self.max_dlogits:.2e}  "
            f"actions {'identical' if self.actions_equal else 'DIFFER'}"
        )


def frozen_axes(model: onnx.ModelProto) -> list[str]:
    """Inputs/outputs whose dynamic axes are not symbolic in the file (empty list = good)."""
    bad = []
    for value in [*model.graph.input, *model.graph.output]:
        dims = value.type.tensor_type.shape.dim
        for axis, name in AXES.get(value.name, {}).items():
            if axis >= len(dims) or dims[axis].dim_param != name:
                bad.append(f"{value.name}[{axis}]")
    return bad


def random_case(n: int, k: int, neighbours: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Positions, presence and a random grouping of n slots with lone and bridging agents.

    About a fifth of the present agents are kept out of every group; groups of up to k
    distinct members are drawn from the rest (at least two groups whenever two agents are
    left), and the second group always contains the first group's leader: a bridge.
    """
    side = max(3, int(2 * np.sqrt(n)))
    pos = rng.integers(0, side, (n, 2))
    present = rng.random(n) > 0.1
    present[0] = True
    live = np.flatnonzero(present)
    lone = rng.choice(live, size=live.size // 5 + (live.size >= 2), replace=False)
    pool = np.setdiff1d(live, lone)
    size = min(k, pool.size)
    groups = np.zeros((0, max(size, 1)), np.int64)
    if size >= 2:
        count = int(rng.integers(2, max(2, pool.size // 2) + 1))
        groups = np.stack([rng.choice(pool, size, replace=False) for _ in range(count)])
        others = pool[pool != groups[0, 0]]
        groups[1] = [*rng.choice(others, size - 1, replace=False), groups[0, 0]]
    return {
        "pos": pos,
        "present": present,
        "groups": groups,
        "neighbours": neighbour_table(pos, present, neighbours),
    }


@torch.no_grad()
def torch_step(
    model: MultiAgentQ, feeds: dict[str, np.ndarray], groups: np.ndarray
) -> dict[str, np.ndarray]:
    """The reference: :meth:`udan.learner.Actor.act`'s computation for one arena, given groups."""
    h, c = (torch.from_numpy(feeds[name]) for name in ("h", "c"))
    feats, (h, c) = model.encoder(
        torch.from_numpy(feeds["obs"])[None], (h, c), torch.from_numpy(feeds["fresh"])[None]
    )
    feats = feats[0]
    out = {"h_out": h.numpy(), "c_out": c.numpy()}
    rounds = []
    if model.spec.communicates:
        if feeds["neighbours"].shape[1]:
            neighbours = torch.from_numpy(feeds["neighbours"])
            out["leader_logits"] = model.leader(feats, neighbours).numpy()
        rounds = merge_rounds([groups], [0])
    q = model.head(feats, model.messages(feats, rounds))
    return {**out, "q": q.numpy(), "action": q.argmax(-1).numpy()}


def parity(
    graph: PolicyGraph, model: MultiAgentQ, sizes=SIZES, steps: int = 4, seed: int = 0
) -> list[SizeResult]:
    """ORT vs torch at each size over ``steps`` consecutive steps, each carrying its own state."""
    spec = model.spec
    rng = np.random.default_rng(seed)
    results = []
    for n in sizes:
        states = {
            side: {name: np.zeros((1, n, spec.hidden), np.float32) for name in ("h", "c")}
            for side in ("ort", "torch")
        }
        dq = dstate = dlogits = 0.0
        equal = True
        groups = rounds = bridges = lone = 0
        for t in range(steps):
            case = random_case(n, spec.group_size, spec.attention_neighbours, rng)
            obs = rng.random((n, spec.obs_dim), dtype=np.float32) * case["present"][:, None]
            fresh = np.ones(n, bool) if t == 0 else rng.random(n) < 0.1
            scored = t % 2 == 0  # odd steps: no neighbours, the graph skips the leader scores
            neighbours = case["neighbours"] if scored else no_neighbours(n)
            base = {"obs": obs, "fresh": fresh, "neighbours": neighbours}
            base.update(round_inputs(case["groups"]))
            forget(states["ort"]["h"], states["ort"]["c"], fresh)
            got = graph.run({**base, **states["ort"]})
            want = torch_step(model, {**base, **states["torch"]}, case["groups"])
            if spec.communicates:  # a formation step's second call: from the features, no encoder
                again = {"h": got["h_out"], "c": got["c_out"], "neighbours": no_neighbours(n)}
                second = graph.run({**base, **again, "encoded": np.ones((), bool)})
                for name in ("q", "h_out", "c_out"):
                    dq = max(dq, float(np.abs(second[name] - want[name]).max()))
                equal &= bool(np.array_equal(second["action"], want["action"]))
            states["ort"] = {"h": got["h_out"], "c": got["c_out"]}
            states["torch"] = {"h": want["h_out"], "c": want["c_out"]}
            if not (spec.communicates and scored):  # a scoring call leaves q and action zero
                dq = max(dq, float(np.abs(got["q"] - want["q"]).max()))
                equal &= bool(np.array_equal(got["action"], want["action"]))
            dstate = max(
                dstate, *(float(np.abs(got[s] - want[s]).max()) for s in ("h_out", "c_out"))
            )
            if spec.communicates and scored:
                diff = np.abs(got["leader_logits"] - want["leader_logits"]).max()
                dlogits = max(dlogits, float(diff))
            counts = np.bincount(case["groups"].ravel(), minlength=n)
            groups += len(case["groups"])
            rounds = max(rounds, len(base["round_groups"]))
            bridges += int((counts >= 2).sum())
            lone += int((case["present"] & (counts == 0)).sum())
        results.append(
            SizeResult(n, steps, groups, rounds, bridges, lone, dq, dstate, dlogits, equal)
        )
    return results


@dataclass
class Report:
    """Everything ``verify`` found; ``ok`` is the verdict."""

    checker: str
    frozen: list[str]
    sizes: list[SizeResult]

    @property
    def ok(self) -> bool:
        return self.checker == "ok" and not self.frozen and all(r.ok for r in self.sizes)

    def lines(self) -> list[str]:
        return [
            f"onnx.checker.check_model(full_check=True): {self.checker}",
            "dynamic axes symbolic: "
            + ("yes" if not self.frozen else f"NO, frozen: {', '.join(self.frozen)}"),
            f"onnxruntime vs torch, tolerance {TOLERANCE:g} (groups, bridges, lone: totals over"
            " the steps; rounds: most in one step):",
            *(f"  {r.line()}" for r in self.sizes),
            "verdict: " + ("PASS" if self.ok else "FAIL"),
        ]

    def to_dict(self) -> dict:
        return {
            "ok": self.ok,
            "checker": self.checker,
            "frozen": self.frozen,
            "sizes": [asdict(r) for r in self.sizes],
        }


def verify(onnx_model: onnx.ModelProto, model: MultiAgentQ, sizes=SIZES, steps: int = 4) -> Report:
    """Run every check on an in-memory ONNX model against the torch ``model``."""
    try:
        onnx.checker.check_model(onnx_model, full_check=True)
        checker = "ok"
    except (onnx.checker.ValidationError, onnx.shape_inference.InferenceError) as err:
        checker = f"FAILED: {str(err).strip().splitlines()[0]}"
    graph = PolicyGraph(onnx_model.SerializeToString())
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small networks: on a busy machine more threads are far slower
    try:
        return Report(checker, frozen_axes(onnx_model), parity(graph, model, sizes, steps))
    finally:
        torch.set_num_threads(threads)
