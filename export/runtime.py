"""Run an exported policy with onnxruntime and numpy only: what the edge computer imports.

:class:`PolicyGraph` is one call of the graph (inputs and outputs as in export/README.md).
:class:`OnnxPolicy` is :class:`udan.learner.Actor` for one arena: it keeps each slot's recurrent
state, forms groups every ``T`` steps with :mod:`udan.envs.grouping` (the same code training
uses) and returns greedy actions. Nothing here imports torch.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort

from export.metadata import check_metadata
from udan.envs.grouping import form_groups, group_rounds, neighbour_table
from udan.envs.observe import ObsSpec

OUTPUTS = ("q", "action", "h_out", "c_out")


def session(path: str | Path | bytes) -> ort.InferenceSession:
    """A CPU session on one intra-op thread: the networks are small, threads only add latency."""
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    model = path if isinstance(path, bytes) else str(path)
    return ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])


def no_neighbours(n: int) -> np.ndarray:
    """A ``neighbours`` input with no columns: the graph skips the leader scores (zeros)."""
    return np.zeros((n, 0), np.int64)


def round_inputs(groups: np.ndarray) -> dict[str, np.ndarray]:
    """``members`` (G, s) in round order and ``round_starts`` (R + 1,) from groups in priority
    order (:func:`udan.envs.grouping.form_groups`); no groups gives G = 0 and R = 0."""
    if len(groups) == 0:
        return {"members": np.zeros((0, 1), np.int64), "round_starts": np.zeros(1, np.int64)}
    rounds = group_rounds(groups)
    starts = np.concatenate([[0], np.cumsum([len(r) for r in rounds])]).astype(np.int64)
    return {"members": groups[np.concatenate(rounds)].astype(np.int64), "round_starts": starts}


class PolicyGraph:
    """One exported policy file in onnxruntime: metadata plus a ``run`` of one graph call."""

    def __init__(self, path: str | Path | bytes) -> None:
        self.session = session(path)
        self.metadata: dict[str, str] = dict(self.session.get_modelmeta().custom_metadata_map)
        self.input_names = [i.name for i in self.session.get_inputs()]
        self.communicates = "members" in self.input_names
        self.outputs = list(OUTPUTS) + (["leader_logits"] if self.communicates else [])

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Outputs by name for ``feeds`` by name (extra feeds, e.g. groups for a baseline, are
        ignored so every algorithm can be driven alike)."""
        feeds = {name: feeds[name] for name in self.input_names}
        return dict(zip(self.outputs, self.session.run(self.outputs, feeds), strict=True))


class OnnxPolicy:
    """Greedy actions for one arena of N slots, step after step (the edge's policy).

    Refuses (``MetadataError``) a file whose metadata does not fit this code or ``expected``.
    At a group-formation step the graph runs twice: once for the leader scores, once with the
    groups formed from them (group formation is numpy, between the two; export/README.md).
    """

    def __init__(self, path: str | Path | bytes, expected: ObsSpec | None = None) -> None:
        self.graph = PolicyGraph(path)
        meta = self.graph.metadata
        check_metadata(meta, expected)
        self.hidden = int(meta["hidden"])
        self.k = int(meta["group_size"])
        self.interval = int(meta["group_interval"])
        self.threshold = float(meta["leader_threshold"])
        self.neighbours = int(meta["attention_neighbours"])
        self.reset(0)

    def reset(self, slots: int) -> None:
        """Forget every agent's memory and the groups; the next step forms groups."""
        self.h = np.zeros((slots, self.hidden), np.float32)
        self.c = np.zeros((slots, self.hidden), np.float32)
        self.groups = np.zeros((0, 0), np.int64)
        self.rounds = round_inputs(self.groups)
        self.t = 0
        self.reform = False
        self.q: np.ndarray | None = None

    def act(
        self, obs: np.ndarray, present: np.ndarray, pos: np.ndarray, fresh: np.ndarray
    ) -> np.ndarray:
        """Greedy actions (N,) from ``obs`` (N, D) float32, ``present`` (N,), cell ``pos`` (N, 2)
        and ``fresh`` (N,) (slots whose agent is new: their memory starts from zero). A fleet
        that grew since the last step gets zero state for its new slots."""
        n = len(obs)
        if n != len(self.h):
            self._resize(n)
        feeds = {"obs": obs, "h": self.h, "c": self.c, "fresh": fresh}
        if self.graph.communicates:
            feeds["neighbours"] = no_neighbours(n)
            stale = len(self.groups) > 0 and not present[self.groups].all()
            if self.reform or self.t % self.interval == 0 or stale:
                self.reform = False
                table = neighbour_table(pos, present, self.neighbours)
                no_groups = round_inputs(self.groups[:0])
                logits = self.graph.run({**feeds, "neighbours": table, **no_groups})
                prob = 1.0 / (1.0 + np.exp(-logits["leader_logits"]))
                self.groups = form_groups(pos, present, prob, self.k, self.threshold, near=table)
                self.rounds = round_inputs(self.groups)
            feeds.update(self.rounds)
        out = self.graph.run(feeds)
        self.h, self.c, self.q = out["h_out"], out["c_out"], out["q"]
        self.t += 1
        return out["action"]

    def _resize(self, n: int) -> None:
        keep = min(n, len(self.h))
        for name in ("h", "c"):
            grown = np.zeros((n, self.hidden), np.float32)
            grown[:keep] = getattr(self, name)[:keep]
            setattr(self, name, grown)
        self.groups = np.zeros((0, 0), np.int64)  # they may name slots that are gone
        self.rounds = round_inputs(self.groups)
        self.reform = True
