"""Checkpoint -> one ONNX graph: encoder, leader scores, a Loop over bridge rounds, Q head.

The pieces with weights are traced from the model's own modules (``torch.onnx.export``, the
TorchScript exporter: on this torch the dynamo exporter specialises the group width ``s`` of the
BiLSTM input to the traced value). The pieces are then joined by hand: the communication round
becomes the body of an ONNX ``Loop`` over ``round_starts``, so one graph handles any number of
rounds, groups and agents. Layout and reasons: export/README.md.
"""

from __future__ import annotations

import io
import warnings
from collections.abc import Mapping

import onnx
import torch
from onnx import TensorProto, helper
from torch import nn

from udan.learner import MultiAgentQ

OPSET = 18

#: Symbolic name of every dynamic axis, per input and output of the joined graph.
AXES: dict[str, dict[int, str]] = {
    "obs": {0: "agents"},
    "h": {0: "agents"},
    "c": {0: "agents"},
    "fresh": {0: "agents"},
    "neighbours": {0: "agents", 1: "neighbour_slots"},
    "members": {0: "groups", 1: "group_slots"},
    "round_starts": {0: "rounds_plus_one"},
    "q": {0: "agents"},
    "action": {0: "agents"},
    "h_out": {0: "agents"},
    "c_out": {0: "agents"},
    "leader_logits": {0: "agents"},
}


class _Encode(nn.Module):
    """Encoder step: MLP + LSTM, memory zeroed for fresh agents (as ``AgentEncoder.forward``)."""

    def __init__(self, model: MultiAgentQ) -> None:
        super().__init__()
        self.encoder = model.encoder

    def forward(self, obs, h, c, fresh):
        state = self.encoder.forget((h[None], c[None]), fresh)
        feats, (h_out, c_out) = self.encoder(obs[None], state)
        return feats[0], h_out[0], c_out[0]


class _Round(nn.Module):
    """One round of disjoint groups (eqs. 2-3): members' encodings go through the BiLSTM."""

    def __init__(self, model: MultiAgentQ) -> None:
        super().__init__()
        self.comm = model.comm

    def forward(self, enc, members):
        return self.comm.round(enc, members)


class _Head(nn.Module):
    """Message (final encoding of grouped agents, zero otherwise), Q head and greedy action."""

    def __init__(self, model: MultiAgentQ) -> None:
        super().__init__()
        self.model = model

    def forward(self, feats, enc, members):
        if self.model.spec.communicates:
            grouped = torch.zeros(feats.shape[0], dtype=torch.bool)
            grouped = grouped.index_put((members.reshape(-1),), torch.tensor(True))
            message = torch.where(grouped[:, None], enc, torch.zeros_like(enc))
        else:
            message = self.model.messages(feats, [])
        q = self.model.head(feats, message)
        return q, q.argmax(-1)


def _trace(
    module: nn.Module, args: tuple, inputs: list[str], outputs: list[str]
) -> onnx.GraphProto:
    axes = {name: AXES.get(name, {0: "agents"}) for name in inputs + outputs}
    buf = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
        torch.onnx.export(
            module.eval(),
            args,
            buf,
            dynamo=False,
            opset_version=OPSET,
            input_names=inputs,
            output_names=outputs,
            dynamic_axes=axes,
        )
    return onnx.load_from_string(buf.getvalue()).graph


def _inline(
    graph: onnx.GraphProto, prefix: str, names: Mapping[str, str]
) -> tuple[list[onnx.NodeProto], list[onnx.TensorProto]]:
    """The piece's nodes and weights with inner names prefixed and its inputs/outputs renamed,
    ready to sit in another graph."""

    def rename(name: str) -> str:
        return names.get(name, f"{prefix}/{name}") if name else name

    nodes = []
    for node in graph.node:
        node = onnx.NodeProto.FromString(node.SerializeToString())
        node.input[:] = [rename(n) for n in node.input]
        node.output[:] = [rename(n) for n in node.output]
        node.name = f"{prefix}/{node.name}"
        nodes.append(node)
    weights = []
    for init in graph.initializer:
        init = onnx.TensorProto.FromString(init.SerializeToString())
        init.name = rename(init.name)
        weights.append(init)
    return nodes, weights


def _value(name: str, elem: int, dims: list[int | str | None]) -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info(name, elem, dims)


def build_graph(model: MultiAgentQ, metadata: Mapping[str, str]) -> onnx.ModelProto:
    """The policy of ``model`` as one ONNX model with ``metadata`` in ``metadata_props``."""
    spec = model.spec
    n, k, hidden = 4, max(spec.group_size, 2), spec.hidden
    state = torch.zeros(n, hidden)
    members = torch.arange(k)[None, :] % n
    model = model.eval()

    encode = ["obs", "h", "c", "fresh", "feats", "h_out", "c_out"]
    nodes, weights = _inline(
        _trace(
            _Encode(model),
            (torch.rand(n, spec.obs_dim), state, state, torch.zeros(n, dtype=torch.bool)),
            encode[:4],
            encode[4:],
        ),
        "encode",
        {name: name for name in encode},
    )
    head_nodes, head_weights = _inline(
        _trace(_Head(model), (state, state, members), ["feats", "enc", "members"], ["q", "a"]),
        "head",
        {"feats": "feats", "enc": "comm_out", "members": "members", "q": "q", "a": "action"},
    )
    weights += head_weights
    if spec.communicates:
        leader, leader_weights = _leader_branches(model, state)
        body, body_weights = _round_loop_body(model, state, members)
        weights += leader_weights + body_weights
        nodes += [
            *leader,
            helper.make_node("Constant", [], ["one"], value_int=1),
            helper.make_node("Constant", [], ["go"], value=_scalar("go", TensorProto.BOOL, True)),
            helper.make_node("Size", ["round_starts"], ["n_starts"]),
            helper.make_node("Sub", ["n_starts", "one"], ["n_rounds"]),
            helper.make_node("Loop", ["n_rounds", "go", "feats"], ["comm_out"], body=body),
        ]
    nodes += head_nodes

    f32, i64 = TensorProto.FLOAT, TensorProto.INT64
    inputs = [
        _value("obs", f32, ["agents", spec.obs_dim]),
        _value("h", f32, ["agents", hidden]),
        _value("c", f32, ["agents", hidden]),
        _value("fresh", TensorProto.BOOL, ["agents"]),
    ]
    outputs = [
        _value("q", f32, ["agents", spec.n_actions]),
        _value("action", i64, ["agents"]),
        _value("h_out", f32, ["agents", hidden]),
        _value("c_out", f32, ["agents", hidden]),
    ]
    if spec.communicates:
        inputs += [
            _value("neighbours", i64, ["agents", "neighbour_slots"]),
            _value("members", i64, ["groups", "group_slots"]),
            _value("round_starts", i64, ["rounds_plus_one"]),
        ]
        outputs.append(_value("leader_logits", f32, ["agents"]))
    graph = helper.make_graph(nodes, f"udan_{spec.algo}_policy", inputs, outputs, weights)
    onnx_model = helper.make_model(
        graph,
        opset_imports=[helper.make_opsetid("", OPSET)],
        producer_name="udan-export",
        doc_string="udan-edge policy; inputs, outputs and use: export/README.md",
    )
    onnx_model.ir_version = min(onnx_model.ir_version, 10)  # loadable by older onnxruntimes
    helper.set_model_props(onnx_model, dict(metadata))
    return onnx_model


def _scalar(name: str, elem: int, value: object) -> onnx.TensorProto:
    return helper.make_tensor(name, elem, [], [value])


def _leader_branches(
    model: MultiAgentQ, state: torch.Tensor
) -> tuple[list[onnx.NodeProto], list[onnx.TensorProto]]:
    """``leader_logits`` under an ``If``: computed when ``neighbours`` has columns, else zeros.

    Leader scores are only needed at group-formation steps; every other call passes
    ``neighbours`` with no columns and skips the attention.
    """
    neighbours = torch.arange(state.shape[0])[:, None].repeat(1, 2)
    nodes, weights = _inline(
        _trace(model.leader, (state, neighbours), ["feats", "neighbours"], ["logits"]),
        "leader",
        {"feats": "feats", "neighbours": "neighbours", "logits": "scores"},
    )
    f32 = TensorProto.FLOAT
    scored = helper.make_graph(nodes, "scored", [], [_value("scores", f32, ["agents"])])
    unscored = helper.make_graph(
        [
            helper.make_node("Shape", ["feats"], ["n_agents"], end=1),
            helper.make_node(
                "ConstantOfShape",
                ["n_agents"],
                ["zeros"],
                value=helper.make_tensor("", f32, [1], [0]),
            ),
        ],
        "unscored",
        [],
        [_value("zeros", f32, ["agents"])],
    )
    nodes = [
        helper.make_node("Shape", ["neighbours"], ["nb_width"], start=1, end=2),
        helper.make_node("Constant", [], ["no_width"], value_ints=[0]),
        helper.make_node("Greater", ["nb_width", "no_width"], ["nb_wanted"]),
        helper.make_node("Squeeze", ["nb_wanted"], ["score"]),
        helper.make_node(
            "If", ["score"], ["leader_logits"], then_branch=scored, else_branch=unscored
        ),
    ]
    return nodes, weights


def _round_loop_body(
    model: MultiAgentQ, state: torch.Tensor, members: torch.Tensor
) -> tuple[onnx.GraphProto, list[onnx.TensorProto]]:
    """Loop body for round ``i``: members[round_starts[i]:round_starts[i+1]] through the BiLSTM.

    The weights are returned separately: they live in the outer graph (a body may read outer
    values), so the file holds them once.
    """
    nodes, weights = _inline(
        _trace(_Round(model), (state, members), ["enc", "members"], ["out"]),
        "round",
        {"enc": "enc_in", "members": "round_members", "out": "enc_next"},
    )
    i64 = TensorProto.INT64
    head = [
        helper.make_node("Constant", [], ["r_axis"], value_ints=[0]),
        helper.make_node("Constant", [], ["r_one"], value_ints=[1]),
        helper.make_node("Unsqueeze", ["i", "r_axis"], ["i_1d"]),
        helper.make_node("Add", ["i_1d", "r_one"], ["next_1d"]),
        helper.make_node("Gather", ["round_starts", "i_1d"], ["start"]),
        helper.make_node("Gather", ["round_starts", "next_1d"], ["end"]),
        helper.make_node("Slice", ["members", "start", "end", "r_axis"], ["round_members"]),
        helper.make_node("Identity", ["cond_in"], ["cond_out"]),
    ]
    body = helper.make_graph(
        head + nodes,
        "comm_round",
        [
            _value("i", i64, []),
            _value("cond_in", TensorProto.BOOL, []),
            _value("enc_in", TensorProto.FLOAT, ["agents", model.spec.hidden]),
        ],
        [
            _value("cond_out", TensorProto.BOOL, []),
            _value("enc_next", TensorProto.FLOAT, ["agents", model.spec.hidden]),
        ],
    )
    return body, weights
