"""GCTDE-UDAN networks (paper §IV-A, Fig. 2): one set of weights shared by every agent.

- :class:`AgentEncoder`: observation -> MLP -> LSTM cell -> feature ``l_i`` (state per agent).
- :class:`LeaderScorer`: self-attention over the agents' features (eq. 1), a fully connected
  layer and a sigmoid -> leader probability ``p_i`` (eqs. 5-6).
- :class:`GroupComm`: a bidirectional LSTM over each group's members gives each a message; the
  groups of one round are disjoint and run as one batch, rounds run in order so an agent in
  several groups carries what it learnt in one group into the next (eqs. 2-3).
- :class:`QHead`: ``Q(o_i, message_i)``; with a zero message it is ``Q_s`` (eq. 4).
- :class:`SetMixer`: monotonic mixing of any number of agent Qs without a global state.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


class AgentEncoder(nn.Module):
    """Per-agent MLP + LSTM; the recurrent state is kept per agent id by the caller."""

    def __init__(self, obs_dim: int, hidden: int) -> None:
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(obs_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU()
        )
        self.lstm = nn.LSTM(hidden, hidden)
        self.hidden = hidden

    def initial_state(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        zeros = torch.zeros(1, n, self.hidden)
        return zeros, zeros.clone()

    def forward(
        self,
        obs: torch.Tensor,
        state: tuple[torch.Tensor, torch.Tensor],
        fresh: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """``obs`` (T, M, D), state (1, M, H) each -> features (T, M, H), new state.

        ``fresh`` (T, M) marks agents that are new at a step: their memory starts from zero.
        The whole sequence runs as one fused LSTM call unless agents join after step 0.
        """
        x = self.mlp(obs)
        if fresh is None:
            return self.lstm(x, state)
        if not fresh[1:].any():
            return self.lstm(x, self.forget(state, fresh[0]))
        outs = []
        for t in range(x.shape[0]):
            out, state = self.lstm(x[t : t + 1], self.forget(state, fresh[t]))
            outs.append(out)
        return torch.cat(outs), state

    @staticmethod
    def forget(state, fresh: torch.Tensor):
        keep = (~fresh).to(state[0].dtype)[None, :, None]
        return state[0] * keep, state[1] * keep


class LeaderScorer(nn.Module):
    """Scaled dot-product self-attention of each agent over its neighbours, FC, sigmoid.

    Each agent attends over itself and its nearest agents (``neighbours``, from
    :func:`udan.envs.grouping.nearest`): what a car could hear, and O(N) for any fleet size.
    """

    def __init__(self, hidden: int, attn_dim: int) -> None:
        super().__init__()
        self.query = nn.Linear(hidden, attn_dim)
        self.key = nn.Linear(hidden, attn_dim)
        self.value = nn.Linear(hidden, attn_dim)
        self.out = nn.Linear(attn_dim + hidden, 1)

    def forward(self, feats: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
        """``feats`` (M, H) of all agents, ``neighbours`` (M, K) rows into them (-1 = none,
        column 0 = the agent itself) -> leader logits (M,)."""
        valid = neighbours >= 0
        valid[:, 0] = True  # itself (an absent slot's row is ignored, but must stay finite)
        keys = self.key(feats)[neighbours.clamp(min=0)]  # (M, K, A)
        values = self.value(feats)[neighbours.clamp(min=0)]
        q = self.query(feats)[:, None, :]  # (M, 1, A)
        scores = (q * keys).sum(-1) / keys.shape[-1] ** 0.5
        attn = torch.softmax(scores.masked_fill(~valid, float("-inf")), dim=-1)
        attended = (attn[..., None] * values).sum(1)
        return self.out(torch.cat([attended, feats], dim=-1)).squeeze(-1)


class GroupComm(nn.Module):
    """Bidirectional LSTM over each group's members (leader first), round after round."""

    def __init__(self, hidden: int) -> None:
        super().__init__()
        self.lstm = nn.LSTM(hidden, hidden // 2, batch_first=True, bidirectional=True)
        self.proj = nn.Linear(2 * (hidden // 2), hidden)

    def encode_groups(self, members: torch.Tensor) -> torch.Tensor:
        """Members' features (G, s, H), leader first -> their updated encodings (G, s, H)."""
        out, _ = self.lstm(members)
        return self.proj(out)

    def round(self, enc: torch.Tensor, members: torch.Tensor) -> torch.Tensor:
        """One round of disjoint groups (G, s): their members' encodings updated (eqs. 2-3)."""
        updated = self.encode_groups(enc[members])
        return enc.index_put((members.reshape(-1),), updated.reshape(-1, enc.shape[-1]))

    def forward(self, feats: torch.Tensor, rounds: list[torch.Tensor]) -> torch.Tensor:
        """``feats`` (M, H) of all agents; ``rounds``: per round a (G, s) tensor of member rows.

        Returns messages (M, H): zero for agents in no group. Within a round the groups are
        disjoint, so one batched LSTM call updates them all.
        """
        enc = feats
        grouped = torch.zeros(feats.shape[0], dtype=torch.bool)
        for members in rounds:
            if members.numel() == 0:
                continue
            enc = self.round(enc, members)
            grouped[members.reshape(-1)] = True
        return torch.where(grouped[:, None], enc, torch.zeros_like(enc))


class QHead(nn.Module):
    """Local action values from an agent's feature and its message (zero message -> Q_s)."""

    def __init__(self, hidden: int, n_actions: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(2 * hidden, hidden), nn.ReLU(), nn.Linear(hidden, n_actions)
        )

    def forward(self, feats: torch.Tensor, message: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([feats, message], dim=-1))


class SetMixer(nn.Module):
    """``Q_tot = |w2| . elu(sum_i |W1(l_i)| Q_i + b1) + b2`` over the present agents.

    Non-negative weights and a monotonic activation make Q_tot monotonic in every Q_i (the QMIX
    condition behind eq. 21); the sum over agents takes any N and padded agents add nothing.
    Weights come from each agent's own feature instead of a global state (paper §IV-A-3).
    """

    def __init__(self, hidden: int, mix_dim: int) -> None:
        super().__init__()
        self.w1 = nn.Linear(hidden, mix_dim)
        self.b1 = nn.Parameter(torch.zeros(mix_dim))
        self.w2 = nn.Parameter(torch.rand(mix_dim) * 0.1)
        self.b2 = nn.Parameter(torch.zeros(1))

    def forward(self, q: torch.Tensor, feats: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """``q`` (B, N), ``feats`` (B, N, H), ``mask`` (B, N) -> Q_tot (B,)."""
        w1 = self.w1(feats).abs() * mask[..., None]
        hidden = F.elu((w1 * q.masked_fill(~mask, 0.0)[..., None]).sum(1) + self.b1)
        return hidden @ self.w2.abs() + self.b2

    @torch.no_grad()
    def start_as_sum(self, offset: float = 100.0) -> None:
        """Start as VDN: ``Q_tot = sum_i Q_i`` wherever that sum is above ``-offset``.

        Every agent's weight is 1 whatever its feature (W1's rows 0, its bias 1), the hidden
        units' bias lifts the sum into ELU's linear part and the output's bias takes it off again;
        gradient then moves the weights away from the sum as training asks.
        """
        self.w1.weight.zero_()
        self.w1.bias.fill_(1.0)
        self.b1.fill_(offset)
        self.w2.fill_(1.0 / self.w2.numel())
        self.b2.fill_(-offset)
