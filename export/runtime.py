"""Run an exported policy with onnxruntime and numpy only: what the edge computer imports.

:class:`PolicyGraph` is one call of the graph (inputs and outputs as in export/README.md);
:class:`BoundGraph` is the same graph bound to buffers for calls step after step.
:class:`OnnxPolicy` is :class:`udan.learner.Actor` for one arena: it keeps each slot's recurrent
state, forms groups every ``T`` steps with :mod:`udan.envs.grouping` (the same code training
uses) and returns greedy actions. Nothing here imports torch.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnxruntime as ort

from udan.envs.grouping import form_groups, neighbour_table, round_order
from udan.envs.observe import ObsSpec
from udan.export.metadata import MetadataError, check_metadata

OUTPUTS = ("q", "action", "h_out", "c_out")
NOT_ENCODED = np.zeros((), bool)
"""The ``encoded`` input of every call but a formation step's second: run the encoder."""


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
    """``members`` (s, G) and ``round_groups`` (R,) from groups (G, s) in priority order
    (:func:`udan.envs.grouping.form_groups`): the groups as columns, leader first, listed round
    after round, round r being the ``round_groups[r]`` columns after those of earlier rounds.
    No groups gives G = 0 and R = 0."""
    order, sizes = round_order(groups)
    return {"members": np.ascontiguousarray(groups[order].T, np.int64), "round_groups": sizes}


def forget(h: np.ndarray, c: np.ndarray, fresh: np.ndarray) -> None:
    """Zero, in place, the state (1, N, hidden) of fresh slots (a new agent): its memory
    starts empty."""
    if fresh.any():
        h[:, fresh] = 0.0
        c[:, fresh] = 0.0


def _put(buffer: np.ndarray, array: np.ndarray) -> None:
    """``array`` into a bound ``buffer``, unless it is that buffer (written in place)."""
    if array is not buffer:
        np.copyto(buffer, array)


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
        ignored so every algorithm can be driven alike; ``encoded`` is false unless given)."""
        feeds = {"encoded": NOT_ENCODED, **feeds}
        feeds = {name: feeds[name] for name in self.input_names}
        return dict(zip(self.outputs, self.session.run(self.outputs, feeds), strict=True))


class BoundGraph:
    """The graph bound to buffers of N slots, as a running edge calls it: a step's observations
    are in a bound buffer (:attr:`obs`: written there in place, or copied in) and it runs.

    Binding inputs anew costs onnxruntime about as much as a layer of these networks, so
    nothing is rebound between group formations: two bindings take turns, each reading the
    state (h, c) the other one wrote. A UDAN graph has two more, taking turns the same way,
    for the scoring call of a formation step (``neighbours`` bound to a table, no groups).
    ``q`` and ``action`` are overwritten by every call.
    """

    def __init__(self, graph: PolicyGraph, h: np.ndarray, c: np.ndarray) -> None:
        n = h.shape[1]
        self.graph = graph
        self.obs = np.zeros((n, int(graph.metadata["obs_dim"])), np.float32)
        self.states = [(h, c), (np.empty_like(h), np.empty_like(c))]
        self.q = np.zeros((n, len(json.loads(graph.metadata["actions"]))), np.float32)
        self.action = np.zeros(n, np.int64)
        # The bindings point into these arrays: they live as long as this object.
        self.inputs: dict[str, np.ndarray] = {"obs": self.obs}
        self.outputs: dict[str, np.ndarray] = {"q": self.q, "action": self.action}
        self.scoring: list[ort.IOBinding] = []
        if graph.communicates:
            self.encoded = np.zeros((), bool)
            self.inputs["encoded"] = self.encoded
            self.inputs["neighbours"] = no_neighbours(n)
            self.inputs.update(round_inputs(np.zeros((0, 0), np.int64)))
            self.leader_logits = np.zeros(n, np.float32)
            self.outputs["leader_logits"] = self.leader_logits
            self.table = np.full((n, int(graph.metadata["attention_neighbours"])), -1, np.int64)
            score_inputs = {**self.inputs, "encoded": NOT_ENCODED, "neighbours": self.table}
            self.scoring = [self._bind(turn, score_inputs) for turn in (0, 1)]
        self.bindings = [self._bind(turn, self.inputs) for turn in (0, 1)]
        self.turn = 0

    def _bind(self, turn: int, inputs: dict[str, np.ndarray]) -> ort.IOBinding:
        binding = self.graph.session.io_binding()
        (h_in, c_in), (h_out, c_out) = self.states[turn], self.states[1 - turn]
        for name, array in {**inputs, "h": h_in, "c": c_in}.items():
            binding.bind_cpu_input(name, array)
        for name, array in {**self.outputs, "h_out": h_out, "c_out": c_out}.items():
            binding.bind_ortvalue_output(name, ort.OrtValue.ortvalue_from_numpy(array))
        return binding

    @property
    def state(self) -> tuple[np.ndarray, np.ndarray]:
        """(h, c), each (1, N, hidden): what the next call reads, the last call's output."""
        return self.states[self.turn]

    def bind_groups(self, groups: np.ndarray) -> None:
        """Groups (G, s) in priority order for the calls from now on. Copied into the bound
        buffers when they have the same shapes (a steady fleet: binding costs ~10 µs an
        input), bound anew otherwise."""
        rounds = round_inputs(groups)
        if all(rounds[name].shape == self.inputs[name].shape for name in rounds):
            for name, array in rounds.items():
                np.copyto(self.inputs[name], array)
            return
        self.inputs.update(rounds)
        for binding in self.bindings:
            for name, array in rounds.items():
                binding.bind_cpu_input(name, array)

    def run(self, obs: np.ndarray) -> np.ndarray:
        """One graph call on ``obs`` (N, D), which may be the bound buffer :attr:`obs` itself
        (nothing is copied then); returns ``action`` (N,)."""
        _put(self.obs, obs)
        return self._call(self.bindings)

    def score(self, obs: np.ndarray, table: np.ndarray) -> np.ndarray:
        """The first call of a formation step: encode ``obs`` and score leaders over the
        neighbour ``table`` (N, K); returns ``leader_logits`` (N,). The state is now this
        step's features: :meth:`run_encoded` finishes the step with the groups. Either may be
        the bound buffer itself (:attr:`obs`, :attr:`table`)."""
        _put(self.obs, obs)
        _put(self.table, table)
        self._call(self.scoring)
        return self.leader_logits

    def run_encoded(self) -> np.ndarray:
        """The second call of a formation step: the groups' messages and the actions from the
        features :meth:`score` left in the state (the encoder is not run again)."""
        self.encoded[()] = True
        try:
            return self._call(self.bindings)
        finally:
            self.encoded[()] = False

    def rehearse(self, obs: np.ndarray, table: np.ndarray | None = None) -> None:
        """The call :meth:`run` (or, given a neighbour ``table``, :meth:`score`) would make,
        with nothing kept: it writes only what the next real call overwrites before reading
        (the other turn's state, ``q``, ``action``, the leader scores), and the turn stays."""
        _put(self.obs, obs)
        if table is not None and self.scoring:
            _put(self.table, table)
            self.graph.session.run_with_iobinding(self.scoring[self.turn])
        else:
            self.graph.session.run_with_iobinding(self.bindings[self.turn])

    def _call(self, bindings: list[ort.IOBinding]) -> np.ndarray:
        self.graph.session.run_with_iobinding(bindings[self.turn])
        self.turn = 1 - self.turn
        return self.action


class OnnxPolicy:
    """Greedy actions for one arena of N slots, step after step (the edge's policy).

    Refuses (``MetadataError``) a file whose metadata does not fit this code, ``expected`` or
    ``env``; :meth:`act` refuses observations of another width (ValueError, saying what it wants).
    At a group-formation step the graph runs twice: once for the features and leader scores,
    once more from those features with the groups formed from them (group formation is numpy,
    between the two; export/README.md).
    """

    def __init__(
        self, path: str | Path | bytes, expected: ObsSpec | None = None, env: str | None = None
    ) -> None:
        self.graph = PolicyGraph(path)
        meta = self.graph.metadata
        check_metadata(meta, expected)
        if env is not None and meta["env"] != env:
            raise MetadataError(f"the policy was trained on {meta['env']}, not {env}")
        self.width = int(meta["obs_dim"])
        self._expects = f"({meta['env']}) expects observations (N, {self.width}) float32"
        self.hidden = int(meta["hidden"])
        self.k = int(meta["group_size"])
        self.interval = int(meta["group_interval"])
        self.threshold = float(meta["leader_threshold"])
        self.neighbours = int(meta["attention_neighbours"])
        self._steps: BoundGraph | None = None
        self.reset(0)

    def reset(self, slots: int) -> None:
        """Forget every agent's memory and the groups; the next step forms groups. The graph's
        bindings are kept when the number of slots is unchanged (binding anew costs ~0.3 ms)."""
        if self._steps is not None and len(self._steps.obs) == slots:
            for state in self._steps.state:
                state.fill(0.0)
        else:
            state = np.zeros((1, slots, self.hidden), np.float32)
            self._steps = BoundGraph(self.graph, state, state.copy())
        self.groups = np.zeros((0, 0), np.int64)
        self.t = 0
        self.reform = False
        self.q: np.ndarray | None = None
        self.formed = False  # whether the last step formed groups (two graph calls)

    @property
    def h(self) -> np.ndarray:
        """Each slot's LSTM state h (1, N, hidden) as the next step starts from it."""
        return self._steps.state[0]

    @property
    def c(self) -> np.ndarray:
        """Each slot's LSTM cell state c (1, N, hidden) as the next step starts from it."""
        return self._steps.state[1]

    def act(
        self, obs: np.ndarray, present: np.ndarray, pos: np.ndarray, fresh: np.ndarray
    ) -> np.ndarray:
        """Greedy actions (N,) from ``obs`` (N, D) float32, ``present`` (N,), cell ``pos`` (N, 2)
        and ``fresh`` (N,) (slots whose agent is new: their memory starts from zero). A fleet
        that grew since the last step gets zero state for its new slots."""
        if obs.ndim != 2 or obs.shape[1] != self.width:
            raise ValueError(f"observations of shape {obs.shape}: this policy {self._expects}")
        n = len(obs)
        if n != self._steps.obs.shape[0]:
            self._resize(n)
        if self.t:  # the first step after a reset starts from zeros anyway
            forget(*self._steps.state, fresh)
        self.formed = self._forms_groups(present)
        if self.formed:
            self.reform = False
            table = neighbour_table(pos, present, self.neighbours, out=self._steps.table)
            self.groups = self._form(pos, present, table, self._steps.score(obs, table))
            self._steps.bind_groups(self.groups)
            return self._done(self._steps.run_encoded())
        return self._done(self._steps.run(obs))

    def observations(self, slots: int) -> np.ndarray:
        """The bound observation buffer (``slots``, D) of the next :meth:`act`: observations
        written into it in place are not copied again (another number of slots binds the
        graph anew, as :meth:`act` would)."""
        if slots != len(self._steps.obs):
            self._resize(slots)
        return self._steps.obs

    def rehearse(self, obs: np.ndarray, present: np.ndarray, pos: np.ndarray) -> bool:
        """Go through the work of :meth:`act` on ``obs`` (the last step's, say) and keep
        nothing: no state, groups or step count change. What it is for: a decision that comes
        after the process sat idle, or after a frame's analysis, runs from cold caches at ~3x
        its warm time (measured), so the edge rehearses while it waits for the deciding frame.
        The groups are formed (a step that forms them is the slowest) but not bound. False,
        doing nothing, for ``obs`` of another number of slots than the graph is bound to (the
        next act binds anew anyway)."""
        if len(obs) != len(self._steps.obs):
            return False
        if self._forms_groups(present):
            table = neighbour_table(pos, present, self.neighbours, out=self._steps.table)
            self._steps.rehearse(obs, table)
            round_inputs(self._form(pos, present, table, self._steps.leader_logits))
        self._steps.rehearse(obs)
        return True

    def rerun(self) -> None:
        """The graph call of a step that keeps its groups, once more on what the last step
        bound (its observations, the state it left, its groups), keeping nothing: onnxruntime
        alone, the bare call that ``bench/decision.py`` holds a whole decision step against."""
        self._steps.graph.session.run_with_iobinding(self._steps.bindings[self._steps.turn])

    def _forms_groups(self, present: np.ndarray) -> bool:
        """A step with ``present`` forms groups: every ``interval`` steps, after a resize, and
        at once when an agent of a group is gone."""
        if not self.graph.communicates:
            return False
        if self.reform or self.t % self.interval == 0:
            return True
        return len(self.groups) > 0 and not present[self.groups].all()

    def _form(
        self, pos: np.ndarray, present: np.ndarray, table: np.ndarray, logits: np.ndarray
    ) -> np.ndarray:
        """Groups in priority order from the leader ``logits`` and the neighbour ``table``."""
        prob = 1.0 / (1.0 + np.exp(-logits))
        return form_groups(pos, present, prob, self.k, self.threshold, near=table)

    def _done(self, actions: np.ndarray) -> np.ndarray:
        self.q = self._steps.q.copy()
        self.t += 1
        return actions.copy()

    def _resize(self, n: int) -> None:
        keep = min(n, self.h.shape[1])
        h, c = (np.zeros((1, n, self.hidden), np.float32) for _ in range(2))
        h[:, :keep], c[:, :keep] = self.h[:, :keep], self.c[:, :keep]
        self._steps = BoundGraph(self.graph, h, c)
        self.groups = np.zeros((0, 0), np.int64)  # they may name slots that are gone
        self.reform = True
