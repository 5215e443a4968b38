"""Checkpoint -> one ONNX graph, written node by node from the model's weights.

For networks this small onnxruntime's cost is mostly a fixed price per node (about a
microsecond) and per ``LSTM`` op (about ten), so the graph is written with as few nodes as the
computation allows rather than traced: Gemm layers, one ONNX ``LSTM`` op for the agents'
memory and one per round for the group BiLSTM, a ``Loop`` over the bridge rounds, and an ``If``
that either scores leaders or runs the Q head. That it computes what the model's own modules
compute is checked on every export (:mod:`udan.export.verify`). Layout and reasons:
export/README.md.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from udan.learner import MultiAgentQ

OPSET = 18

#: Symbolic name of every dynamic axis, per input and output of the graph.
AXES: dict[str, dict[int, str]] = {
    "obs": {0: "agents"},
    "h": {1: "agents"},
    "c": {1: "agents"},
    "neighbours": {0: "agents", 1: "neighbour_slots"},
    "members": {0: "group_width", 1: "groups"},
    "round_groups": {0: "rounds"},
    "q": {0: "agents"},
    "action": {0: "agents"},
    "h_out": {1: "agents"},
    "c_out": {1: "agents"},
    "leader_logits": {0: "agents"},
}

#: Leader-score floor for neighbours that are not there (-1). Finite, unlike the model's -inf:
#: an absent slot's row (all -1) then averages agent 0's value over its K columns, which is
#: what the model's always-valid first column gives it, instead of NaN.
NO_NEIGHBOUR = -1e30
#: The leader attention's weights that the graph holds only as products (folded in float64).
LEADER_FOLDED = (
    "leader.query.weight", "leader.query.bias", "leader.key.weight", "leader.value.weight",
    "leader.value.bias", "leader.out.weight", "leader.out.bias",
)  # fmt: skip

F32, I64, BOOL = TensorProto.FLOAT, TensorProto.INT64, TensorProto.BOOL


class _Graph:
    """Nodes of one (sub)graph being written; weights and names are shared with its parents."""

    def __init__(self, parent: _Graph | None = None) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.weights: list[onnx.TensorProto] = [] if parent is None else parent.weights
        self._count = [0] if parent is None else parent._count
        self._consts: dict[tuple, str] = {} if parent is None else parent._consts

    def sub(self) -> _Graph:
        """A graph for a Loop body or If branch: its weights and constants go to the outer
        graph (a subgraph may read outer values), so the file holds each once."""
        return _Graph(self)

    def _name(self, hint: str) -> str:
        self._count[0] += 1
        return f"{hint}_{self._count[0]}"

    def op(self, op_type: str, *inputs: str, out: str | list[str] | None = None, **attrs) -> str:
        """Append a node and return its (first) output: ``out``, or a fresh name."""
        outputs = [out] if isinstance(out, str) else out or [self._name(op_type.lower())]
        self.nodes.append(helper.make_node(op_type, list(inputs), outputs, **attrs))
        return outputs[0]

    def weight(self, hint: str, array: np.ndarray) -> str:
        name = self._name(hint)
        array = np.ascontiguousarray(array) if array.ndim else array  # it makes 0-d arrays 1-d
        self.weights.append(numpy_helper.from_array(array, name))
        return name

    def const(self, *values: int | float, scalar: bool = False) -> str:
        """A small int64 (or float32) constant, one initializer per distinct value."""
        dtype = np.float32 if isinstance(values[0], float) else np.int64
        array = np.array(values[0] if scalar else values, dtype)
        key = (array.dtype.str, array.shape, array.tobytes())
        if key not in self._consts:
            self._consts[key] = self.weight("const", array)
        return self._consts[key]


def _value(name: str, elem: int, dims: list[int | str]) -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info(name, elem, dims)


def _onnx_gates(w: np.ndarray) -> np.ndarray:
    """torch's LSTM gate order (i, f, g, o) along axis 0 -> ONNX's (i, o, f, c)."""
    i, f, g, o = np.split(w, 4, axis=0)
    return np.concatenate([i, o, f, g])


def _lstm_weights(
    w: Mapping[str, np.ndarray], prefix: str, suffixes: tuple[str, ...], inputs: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ONNX ``LSTM`` inputs W, R, B for the directions (``suffixes``) of a torch ``nn.LSTM``;
    W gets zero columns up to ``inputs`` (input columns the LSTM does not see)."""
    ws, rs, bs = [], [], []
    for suffix in suffixes:
        w_ih = _onnx_gates(w[f"{prefix}weight_ih_l0{suffix}"])
        ws.append(np.pad(w_ih, ((0, 0), (0, inputs - w_ih.shape[1]))))
        rs.append(_onnx_gates(w[f"{prefix}weight_hh_l0{suffix}"]))
        biases = (w[f"{prefix}bias_{part}_l0{suffix}"] for part in ("ih", "hh"))
        bs.append(np.concatenate([_onnx_gates(b) for b in biases]))
    return np.stack(ws), np.stack(rs), np.stack(bs)


def build_graph(model: MultiAgentQ, metadata: Mapping[str, str]) -> onnx.ModelProto:
    """The policy of ``model`` as one ONNX model with ``metadata`` in ``metadata_props``."""
    spec = model.spec
    hidden = spec.hidden
    w = {
        name: t.detach().cpu().numpy().astype(np.float32) for name, t in model.state_dict().items()
    }
    g = _Graph()
    feats = _encoder(g, w, hidden, skippable=spec.communicates)
    if spec.communicates:
        _score_or_act(g, w, feats, hidden, spec.n_actions)
    else:
        _head(g, w, feats, hidden, message=None, suffix="")

    state = [1, "agents", hidden]
    inputs = [
        _value("obs", F32, ["agents", spec.obs_dim]),
        _value("h", F32, state),
        _value("c", F32, state),
    ]
    outputs = [
        _value("q", F32, ["agents", spec.n_actions]),
        _value("action", I64, ["agents"]),
        _value("h_out", F32, state),
        _value("c_out", F32, state),
    ]
    if spec.communicates:
        inputs += [
            _value("encoded", BOOL, []),
            _value("neighbours", I64, ["agents", "neighbour_slots"]),
            _value("members", I64, ["group_width", "groups"]),
            _value("round_groups", I64, ["rounds"]),
        ]
        outputs.append(_value("leader_logits", F32, ["agents"]))
    graph = helper.make_graph(g.nodes, f"udan_{spec.algo}_policy", inputs, outputs, g.weights)
    onnx_model = helper.make_model(
        graph,
        opset_imports=[helper.make_opsetid("", OPSET)],
        producer_name="udan-export",
        doc_string="udan-edge policy; inputs, outputs and use: export/README.md",
    )
    onnx_model.ir_version = min(onnx_model.ir_version, 10)  # loadable by older onnxruntimes
    helper.set_model_props(onnx_model, dict(metadata))
    return onnx_model


def _encoder(g: _Graph, w: Mapping[str, np.ndarray], hidden: int, skippable: bool) -> str:
    """MLP, then one step of the model's LSTM from (h, c): writes ``h_out`` and ``c_out`` and
    returns the features (N, hidden), which are ``h_out``.

    ``skippable`` (UDAN): the encoder sits under an ``If`` on the ``encoded`` input. The second
    call of a group-formation step passes the first call's ``h_out``/``c_out`` with ``encoded``
    true: they already are this step's features, so they pass through and the encoder is not
    run again."""
    e = g.sub() if skippable else g
    x = "obs"
    for layer in ("0", "2"):
        weight = e.weight(f"mlp{layer}_w", w[f"encoder.mlp.{layer}.weight"].T)
        x = e.op(
            "Relu",
            e.op("Gemm", x, weight, e.weight(f"mlp{layer}_b", w[f"encoder.mlp.{layer}.bias"])),
        )
    w_ih, w_hh, b = _lstm_weights(w, "encoder.lstm.", ("",), hidden)
    weights = [e.weight("lstm_w", w_ih), e.weight("lstm_r", w_hh), e.weight("lstm_b", b)]
    steps = e.op("Unsqueeze", x, e.const(0))  # (1 step, N, hidden)
    h_c = ["h_new", "c_new"] if skippable else ["h_out", "c_out"]
    e.op("LSTM", steps, *weights, "", "h", "c", out=["", *h_c], hidden_size=hidden)
    if not skippable:
        return g.op("Squeeze", "h_out", g.const(0))
    e.op("Squeeze", "h_new", e.const(0), out="feats_new")
    t = g.sub()
    t.op("Identity", "h", out="h_given")
    t.op("Identity", "c", out="c_given")
    t.op("Squeeze", "h", t.const(0), out="feats_given")
    given = _encoder_branch(t, "encoded", "given", hidden)
    run = _encoder_branch(e, "encode", "new", hidden)
    g.op("If", "encoded", out=["h_out", "c_out", "feats"], then_branch=given, else_branch=run)
    return "feats"


def _encoder_branch(b: _Graph, name: str, suffix: str, hidden: int) -> onnx.GraphProto:
    """One branch of the encoder's ``If``: its nodes, giving ``h_``, ``c_`` and ``feats_`` +
    ``suffix``."""
    state = [1, "agents", hidden]
    outputs = [
        _value(f"h_{suffix}", F32, state),
        _value(f"c_{suffix}", F32, state),
        _value(f"feats_{suffix}", F32, ["agents", hidden]),
    ]
    return helper.make_graph(b.nodes, name, [], outputs)


def _score_or_act(
    g: _Graph, w: Mapping[str, np.ndarray], feats: str, hidden: int, n_actions: int
) -> None:
    """The communication rounds, then an ``If`` on whether ``neighbours`` has columns. A
    scoring call (it has: the first call of a group-formation step, bound with no groups)
    computes ``leader_logits`` and leaves ``q`` and ``action`` zero, as its actions are never
    used: the step's second call acts with the groups. Any other call runs the Q head, and its
    ``leader_logits`` are zero. The rounds' ``Loop`` stays outside the ``If``: nested in a
    branch it cost ~20 µs more a call at N = 5."""
    message = _communicate(g, w, feats, hidden)  # (N, hidden + 1): the flag column last
    scored = g.sub()
    _leader(scored, w, feats)
    rows = scored.op("Shape", feats, end=1)
    _zeros(scored, scored.op("Concat", rows, scored.const(n_actions), axis=0), F32, "q_scored")
    _zeros(scored, rows, I64, "action_scored")
    score = helper.make_graph(
        scored.nodes, "score", [], _outputs(n_actions, "q_scored", "action_scored", "leader_scores")
    )

    acted = g.sub()
    _head(acted, w, feats, hidden, message, suffix="_acted")
    _zeros(acted, acted.op("Shape", feats, end=1), F32, "unscored")
    act = helper.make_graph(
        acted.nodes, "act", [], _outputs(n_actions, "q_acted", "action_acted", "unscored")
    )

    wanted = g.op("Greater", g.op("Size", "neighbours"), g.const(0, scalar=True))
    g.op("If", wanted, out=["q", "action", "leader_logits"], then_branch=score, else_branch=act)


def _zeros(g: _Graph, shape: str, elem: int, out: str) -> None:
    """``out``: zeros of ``elem`` type and the (1-D tensor) ``shape``."""
    value = helper.make_tensor("zero", elem, [1], [0])
    g.op("ConstantOfShape", shape, out=out, value=value)


def _outputs(n_actions: int, q: str, action: str, logits: str) -> list[onnx.ValueInfoProto]:
    """A branch's outputs, named ``q``, ``action``, ``logits``, in the ``If``'s order."""
    return [
        _value(q, F32, ["agents", n_actions]),
        _value(action, I64, ["agents"]),
        _value(logits, F32, ["agents"]),
    ]


def _head(
    g: _Graph,
    w: Mapping[str, np.ndarray],
    feats: str,
    hidden: int,
    message: str | None,
    suffix: str,
) -> None:
    """The Q head on the features and, for UDAN, the message: writes ``q`` and ``action``
    + ``suffix``."""
    w_head = w["head.net.0.weight"].T  # (2 * hidden, hidden): features, then message
    z = g.op(
        "Gemm", feats, g.weight("head_w", w_head[:hidden]), g.weight("head_b", w["head.net.0.bias"])
    )
    if message is not None:
        w_message = np.pad(w_head[hidden:], ((0, 1), (0, 0)))
        z = g.op("Gemm", message, g.weight("head_w_message", w_message), z)
    w_out, b_out = (
        g.weight("head_w_q", w["head.net.2.weight"].T),
        g.weight("head_b_q", w["head.net.2.bias"]),
    )
    q = g.op("Gemm", g.op("Relu", z), w_out, b_out, out=f"q{suffix}")
    g.op("ArgMax", q, axis=1, keepdims=0, out=f"action{suffix}")


def _leader(s: _Graph, w: Mapping[str, np.ndarray], feats: str) -> None:
    """The leader attention over the ``neighbours`` table: writes ``leader_scores`` (N,)."""
    # Folded: a query against W_k f_j + b_k is (W_k^T q) . f_j plus a term equal for every j,
    # which the softmax drops; the value and output layers are linear after the attention
    # weights, which sum to 1, so the attended part of the score is the attention-weighted
    # sum of one number per agent, f_j . (w_out W_v). No key or value is computed, and no
    # attended (N, H) vector either.
    # The folds are products of weight matrices. Computed in float32, their last bits depend
    # on the BLAS kernel the machine picks (so the file's bytes did); in float64, rounded to
    # float32 once, they are the same everywhere.
    f64 = {k: w[k].astype(np.float64) for k in LEADER_FOLDED}
    w_q, b_q = f64["leader.query.weight"], f64["leader.query.bias"]  # (A, H), (A,)
    w_k, w_v = f64["leader.key.weight"], f64["leader.value.weight"]
    scale = w_k.shape[0] ** -0.5
    w_out = f64["leader.out.weight"][0]  # (A + H,): attended, then own features
    w_attended, w_own = w_out[: w_v.shape[0]], w_out[w_v.shape[0] :]
    query = s.op(
        "Gemm",
        feats,
        s.weight("leader_w_query", np.float32((w_q.T @ w_k) * scale)),
        s.weight("leader_b_query", np.float32((b_q @ w_k) * scale)),
    )
    rows = s.op("Max", "neighbours", s.const(0, scalar=True))  # -1 (none) reads row 0, masked
    near = s.op("Gather", feats, rows)  # (N, K, H)
    scores = s.op("MatMul", near, s.op("Unsqueeze", query, s.const(-1)))  # (N, K, 1)
    scores = s.op("Squeeze", scores, s.const(-1))
    there = s.op("GreaterOrEqual", "neighbours", s.const(0, scalar=True))
    scores = s.op("Where", there, scores, s.const(NO_NEIGHBOUR, scalar=True))
    attn = s.op("Softmax", scores, axis=-1)  # (N, K)
    # per agent: what it adds to a score as a neighbour (column 0), and its own part (column 1)
    w_parts = np.float32(np.stack([w_attended @ w_v, w_own], axis=1))  # (H, 2)
    b_own = f64["leader.out.bias"][0] + w_attended @ f64["leader.value.bias"]
    parts = s.op(
        "Gemm",
        feats,
        s.weight("leader_w", w_parts),
        s.weight("leader_b", np.array([0, b_own], np.float32)),
    )
    as_neighbour = s.op("Gather", parts, s.const(0, scalar=True), axis=1)  # (N,)
    own = s.op("Gather", parts, s.const(1, scalar=True), axis=1)
    attended = s.op("Mul", attn, s.op("Gather", as_neighbour, rows))  # (N, K)
    s.op("Add", s.op("ReduceSum", attended, s.const(1), keepdims=0), own, out="leader_scores")


def _communicate(g: _Graph, w: Mapping[str, np.ndarray], feats: str, hidden: int) -> str:
    """Messages (N, hidden + 1, the last column a "grouped" flag): the group BiLSTM round
    after round (a ``Loop``), zero rows for agents in no group.

    The Loop carries ``enc`` (N, hidden + 1): each agent's encoding and the flag. A round is
    the model's BiLSTM as one ONNX ``LSTM`` over the round's groups (s steps, the groups as the
    batch), then its projection, which also sets the flag, scattered back to the members.
    """
    width = w["comm.lstm.weight_hh_l0"].shape[1]
    w_ih, w_hh, b = _lstm_weights(w, "comm.lstm.", ("", "_reverse"), hidden + 1)
    w_proj = np.pad(w["comm.proj.weight"].T, ((0, 0), (0, 1)))  # rows: forward, backward
    b_proj = np.append(w["comm.proj.bias"], np.float32(1.0))  # an updated row is flagged

    r = g.sub()
    members = r.op("SequenceAt", "rounds", "i")  # (s, groups of this round)
    weights = [
        r.weight("comm_lstm_w", w_ih),
        r.weight("comm_lstm_r", w_hh),
        r.weight("comm_lstm_b", b),
    ]
    seq = r.op("Gather", "enc", members)
    seq = r.op("LSTM", seq, *weights, hidden_size=width, direction="bidirectional")
    seq = r.op("Transpose", seq, perm=[0, 2, 1, 3])  # (s, groups, direction, width)
    seq = r.op("Reshape", seq, r.const(-1, 2 * width))
    update = r.op("Gemm", seq, r.weight("comm_w_proj", w_proj), r.weight("comm_b_proj", b_proj))
    slots = r.op("Reshape", members, r.const(-1, 1))
    r.op("ScatterND", "enc", slots, update, out="enc_out")
    body = helper.make_graph(
        r.nodes,
        "comm_round",
        [_value("i", I64, []), _value("go", BOOL, []), _value("enc", F32, ["agents", hidden + 1])],
        [_value("go", BOOL, []), _value("enc_out", F32, ["agents", hidden + 1])],
    )

    enc = g.op("Pad", feats, g.const(0, 0, 0, 1))  # flag column: 0
    g.op("SplitToSequence", "members", "round_groups", axis=1, out="rounds")
    enc = g.op("Loop", g.op("Size", "round_groups"), "", enc, body=body)
    flag = g.op("Slice", enc, g.const(hidden), g.const(hidden + 1), g.const(1))
    return g.op("Mul", enc, flag)
