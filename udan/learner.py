"""Value-based multi-agent learners on one agent network: UDAN and the QMIX/VDN/IQL baselines.

Everything an algorithm changes is here: whether agents communicate (UDAN), how agent Qs are
mixed (set mixer, QMIX hypernetwork over the global state, sum, none), and the losses. The
acting path (:class:`Actor`) is used for training rollouts and for ``udan-eval`` alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from udan.ablations import check_ablation
from udan.envs.grouping import form_groups, group_rounds, hypothetical_groups, neighbour_tables
from udan.nets import AgentEncoder, GroupComm, LeaderScorer, QHead, SetMixer

ALGOS = ("udan", "qmix", "vdn", "iql", "coma")


@dataclass(frozen=True)
class ModelSpec:
    """Shapes and algorithm choices that define a model's weights (saved in checkpoints)."""

    algo: str
    obs_dim: int
    n_actions: int
    hidden: int = 64
    attn_dim: int = 32
    mix_dim: int = 32
    group_size: int = 3
    group_interval: int = 5
    leader_threshold: float = 0.5
    attention_neighbours: int = 8
    """K: each agent's leader attention covers itself and its K-1 nearest agents."""
    state_dim: int = 0
    mix_agents: int = 0
    """QMIX only: the fixed number of agents its hypernetwork mixes (trained at fixed N)."""
    messages: bool = True
    """UDAN only: False builds the same learner without leaders, groups or messages (the
    no-communication control: its Q head always gets a zero message)."""

    @property
    def communicates(self) -> bool:
        return self.algo == "udan" and self.messages


class QMixer(nn.Module):
    """QMIX (Rashid et al.): hypernetworks over the global state give non-negative weights."""

    def __init__(self, state_dim: int, n_agents: int, mix_dim: int) -> None:
        super().__init__()
        self.n_agents, self.mix_dim = n_agents, mix_dim
        self.hyper_w1 = nn.Linear(state_dim, n_agents * mix_dim)
        self.hyper_b1 = nn.Linear(state_dim, mix_dim)
        self.hyper_w2 = nn.Linear(state_dim, mix_dim)
        self.value = nn.Sequential(nn.Linear(state_dim, mix_dim), nn.ReLU(), nn.Linear(mix_dim, 1))

    def forward(self, q: torch.Tensor, state: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        w1 = self.hyper_w1(state).abs().view(-1, self.n_agents, self.mix_dim)
        q = q.masked_fill(~mask, 0.0)[:, : self.n_agents]
        hidden = F.elu(torch.einsum("bn,bnm->bm", q, w1) + self.hyper_b1(state))
        w2 = self.hyper_w2(state).abs()
        return (hidden * w2).sum(-1) + self.value(state).squeeze(-1)


class MultiAgentQ(nn.Module):
    """Shared agent network (+ communication for UDAN) and the algorithm's mixer.

    For COMA the same network is the actor: its outputs are policy logits, whose argmax is the
    greedy action, so acting, evaluation and export treat every algorithm alike.
    """

    def __init__(self, spec: ModelSpec) -> None:
        super().__init__()
        if spec.algo not in ALGOS:
            raise ValueError(f"unknown algo {spec.algo!r}; known: {', '.join(ALGOS)}")
        self.spec = spec
        self.encoder = AgentEncoder(spec.obs_dim, spec.hidden)
        self.head = QHead(spec.hidden, spec.n_actions)
        if spec.communicates:
            self.leader = LeaderScorer(spec.hidden, spec.attn_dim)
            self.comm = GroupComm(spec.hidden)
        if spec.algo == "udan":
            self.mixer = SetMixer(spec.hidden, spec.mix_dim)
        elif spec.algo == "qmix":
            self.mixer = QMixer(spec.state_dim, spec.mix_agents, spec.mix_dim)

    def messages(self, feats: torch.Tensor, rounds: list[torch.Tensor]) -> torch.Tensor:
        if not self.spec.communicates:
            return torch.zeros_like(feats)
        return self.comm(feats, rounds)

    def mix(
        self, q: torch.Tensor, feats: torch.Tensor, state: torch.Tensor, mask: torch.Tensor
    ) -> torch.Tensor:
        """Q_tot (B,) from chosen agent Qs (B, N); IQL has no Q_tot."""
        if self.spec.algo == "udan":
            return self.mixer(q, feats, mask)
        if self.spec.algo == "qmix":
            return self.mixer(q, state, mask)
        if self.spec.algo == "vdn":
            return q.masked_fill(~mask, 0.0).sum(-1)
        raise ValueError(f"{self.spec.algo} has no mixer")


def neighbour_rows(tables: np.ndarray) -> torch.Tensor:
    """Neighbour tables of M arenas (M, N, K) (:func:`neighbour_tables`) as rows into the
    arenas' flattened agents (M * N, K), -1 kept."""
    m, n, count = tables.shape
    offsets = (np.arange(m) * n)[:, None, None]
    return torch.from_numpy(np.where(tables >= 0, tables + offsets, -1).reshape(m * n, count))


def merge_rounds(groups_per_arena: list[np.ndarray], offsets: list[int]) -> list[torch.Tensor]:
    """Rounds of many arenas as one list of (G, s) row-index tensors for :class:`GroupComm`.

    Round r of every arena goes together (arenas share no agent); groups of different sizes
    in one round are listed one size after the other, which is equivalent since they are
    disjoint.
    """
    buckets: dict[tuple[int, int], list[np.ndarray]] = {}
    known: dict[tuple[tuple[int, ...], bytes], list[np.ndarray]] = {}  # groups repeat for T steps
    for groups, offset in zip(groups_per_arena, offsets, strict=True):
        if len(groups) == 0:
            continue
        key = (groups.shape, groups.tobytes())
        if key not in known:
            known[key] = group_rounds(groups)
        for r, idx in enumerate(known[key]):
            buckets.setdefault((r, groups.shape[1]), []).append(groups[idx] + offset)
    return [torch.from_numpy(np.concatenate(buckets[key])) for key in sorted(buckets)]


class Actor:
    """Acts for B arenas with per-slot recurrent state; forms groups every ``interval`` steps.

    ``ablate`` (one of :data:`udan.ablations.ABLATIONS`) changes what it names at acting time;
    ``rng`` draws the random leaders and message shuffles. The last step's features and
    messages are kept (``feats``, ``messages``, each (B*N, H)) for probes.
    """

    def __init__(
        self,
        model: MultiAgentQ,
        batch: int,
        slots: int,
        ablate: str | None = None,
        rng: np.random.Generator | None = None,
    ) -> None:
        if ablate is not None:
            check_ablation(ablate, model.spec.algo, model.spec.communicates, batch)
        self.model, self.batch, self.slots = model, batch, slots
        self.ablate = ablate
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.state = model.encoder.initial_state(batch * slots)
        self.groups: list[np.ndarray] = [np.zeros((0, 0), np.int64)] * batch
        self.rounds: list[torch.Tensor] = []  # the groups' rounds, made when they are formed
        self.feats = self.messages = torch.zeros(0)
        self.leader_explore = 0.0  # training rollouts set it (TrainConfig.leader_explore)
        self.random_actions: np.ndarray | None = None  # ε's draw; None: uniform (.explore)
        self.t = 0

    def reset(self) -> None:
        self.state = self.model.encoder.initial_state(self.batch * self.slots)
        self.groups = [np.zeros((0, 0), np.int64)] * self.batch
        self.rounds = []
        self.t = 0

    @torch.no_grad()
    def values(
        self,
        obs: np.ndarray,
        present: np.ndarray,
        pos: np.ndarray,
        fresh: np.ndarray,
        rng: np.random.Generator | None = None,
    ) -> torch.Tensor:
        """One decision step's outputs (B*N, actions): Q values, or COMA's policy logits.

        Advances each agent's memory (``fresh`` marks slots whose agent is new) and, for UDAN,
        re-forms groups every ``group_interval`` steps or when a member has left. With ``rng``
        and a ``leader_explore`` above 0 (training rollouts), each agent the scorer passes over
        leads anyway with that probability.
        """
        spec = self.model.spec
        feats, self.state = self.model.encoder(
            torch.from_numpy(obs).reshape(1, -1, spec.obs_dim),
            self.state,
            torch.from_numpy(fresh.reshape(1, -1)),
        )
        feats = feats[0]
        if spec.communicates:
            stale = any(len(g) and not present[b][g].all() for b, g in enumerate(self.groups))
            if self.t % spec.group_interval == 0 or stale:
                tables = neighbour_tables(pos, present, spec.attention_neighbours)
                logits = self.model.leader(feats, neighbour_rows(tables))
                prob = torch.sigmoid(logits).view(self.batch, self.slots).numpy()
                prob = self._ablated_leaders(prob, present)
                if self.leader_explore > 0 and rng is not None:
                    explore = present & (rng.random(prob.shape) < self.leader_explore)
                    lead = np.nextafter(np.float32(spec.leader_threshold), np.float32(2))
                    prob = np.where(explore, np.maximum(prob, lead), prob)
                self.groups = [
                    np.flatnonzero(present[b])[:, None]
                    if self.ablate == "groups"
                    else form_groups(
                        pos[b],
                        present[b],
                        prob[b],
                        spec.group_size,
                        spec.leader_threshold,
                        near=tables[b],
                    )
                    for b in range(self.batch)
                ]
                offsets = [b * self.slots for b in range(self.batch)]
                self.rounds = merge_rounds(self.groups, offsets)
        self.t += 1
        self.feats = feats
        self.messages = self._ablated_messages(self.model.messages(feats, self.rounds))
        return self.model.head(feats, self.messages)

    def _ablated_leaders(self, prob: np.ndarray, present: np.ndarray) -> np.ndarray:
        """Leader probabilities (B, N) as the ablation has them (unchanged by default)."""
        threshold = self.model.spec.leader_threshold
        if self.ablate == "leaders=all":
            return np.where(present, prob + 1.0, prob)  # all above the threshold, same order
        if self.ablate not in ("leaders=random", "leaders=top-half", "leaders=random-half"):
            return prob
        out = np.zeros_like(prob)  # below any threshold in (0, 1]: nobody else leads
        for b in range(self.batch):
            slots = np.flatnonzero(present[b])
            if self.ablate == "leaders=random":
                count = int((prob[b, slots] > threshold).sum())
            else:
                count = (slots.size + 1) // 2
            if self.ablate == "leaders=top-half":
                chosen = slots[np.argsort(-prob[b, slots], kind="stable")[:count]]
                out[b, chosen] = 1.0 + prob[b, chosen]  # the scorer's order
            else:
                chosen = self.rng.permutation(slots)[:count]
                out[b, chosen] = 1.0 + self.rng.random(count)  # a random order for bridges too
        return out

    def _ablated_messages(self, messages: torch.Tensor) -> torch.Tensor:
        """Messages (B*N, H) as the ablation has them (unchanged by default)."""
        if self.ablate == "messages=zero":
            return torch.zeros_like(messages)
        if self.ablate != "messages=shuffle":
            return messages
        order = self.rng.permutation(self.batch)  # episode order[i] hears episode order[i+1]
        source = np.empty(self.batch, dtype=np.int64)
        source[order] = np.roll(order, -1)
        per_episode = messages.view(self.batch, self.slots, -1)
        return per_episode[torch.from_numpy(source)].reshape(messages.shape)

    def act(
        self,
        obs: np.ndarray,
        present: np.ndarray,
        pos: np.ndarray,
        fresh: np.ndarray,
        epsilon: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        """Greedy (or epsilon-greedy) actions (B, N)."""
        q = self.values(obs, present, pos, fresh, rng)
        actions = q.argmax(-1).numpy().reshape(self.batch, self.slots)
        if epsilon > 0:
            explore = rng.random(actions.shape) < epsilon
            n_actions = self.model.spec.n_actions
            if self.random_actions is None:
                drawn = rng.integers(0, n_actions, actions.shape)
            else:
                drawn = rng.choice(n_actions, size=actions.shape, p=self.random_actions)
            actions = np.where(explore, drawn, actions)
        return actions

    def padded_groups(self) -> np.ndarray:
        """This step's groups as (B, N, k) slots, -1 padded, for the replay's matrix C."""
        k = self.model.spec.group_size
        out = np.full((self.batch, self.slots, k), -1, dtype=np.int8)
        for b, groups in enumerate(self.groups):
            out[b, : len(groups), : groups.shape[1]] = groups
        return out


LEADER_TARGETS = ("signed", "minmax")


def leader_targets(delta_q: torch.Tensor, mode: str = "signed") -> torch.Tensor:
    """ΔQ of eq. (4) scaled into [0, 1] as the leader classifier's BCE target (eq. 9's ΔQ̂).

    ``minmax`` is the paper's min-max normalisation (all equal -> 0.5): its 0.5 is the midpoint
    of the batch's two most extreme ΔQ, so who leads depends on the tails of each batch.
    ``signed`` divides by the batch's largest |ΔQ| and centres on 0.5, so the target is above
    0.5 exactly when the group's messages raise its members' values (docs/algorithm.md).
    """
    if mode == "minmax":
        lo, hi = delta_q.min(), delta_q.max()
        if hi - lo < 1e-8:
            return torch.full_like(delta_q, 0.5)
        return (delta_q - lo) / (hi - lo)
    scale = delta_q.abs().max()
    if scale < 1e-8:
        return torch.full_like(delta_q, 0.5)
    return 0.5 + 0.5 * delta_q / scale


def hypothetical_delta_q(
    model: MultiAgentQ,
    feats: torch.Tensor,
    pos: np.ndarray,
    present: np.ndarray,
    tables: np.ndarray | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """ΔQ of eq. (4) for every present agent as a leader of its k-1 nearest (features detached).

    ``feats`` (M, N, H) for M arena-steps; ``tables``, their neighbour tables if already made.
    Returns (leader rows into the flat M*N agents, ΔQ).
    """
    m, n, _ = feats.shape
    flat = feats.reshape(m * n, -1).detach()
    leaders, members = [], []
    for i in range(m):
        near = None if tables is None else tables[i]
        groups = hypothetical_groups(pos[i], present[i], model.spec.group_size, near)
        if groups.shape[1] >= 2:
            leaders.append(groups[:, 0] + i * n)
            members.append(groups + i * n)
    if not leaders:
        return torch.zeros(0, dtype=torch.long), torch.zeros(0)
    deltas, rows = [], []
    for size in sorted({g.shape[1] for g in members}):
        idx = torch.from_numpy(np.concatenate([g for g in members if g.shape[1] == size]))
        lead = np.concatenate(
            [le for le, g in zip(leaders, members, strict=True) if g.shape[1] == size]
        )
        with torch.no_grad():
            member_feats = flat[idx]
            msg = model.comm.encode_groups(member_feats)
            q_c = model.head(member_feats, msg).max(-1).values
            q_s = model.head(member_feats, torch.zeros_like(msg)).max(-1).values
        deltas.append((q_c - q_s).mean(-1))
        rows.append(torch.from_numpy(lead))
    return torch.cat(rows), torch.cat(deltas)
