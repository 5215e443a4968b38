"""Who leads, and should they? The leader classifier of a UDAN checkpoint against its targets.

At every group formation of greedy episodes, each present agent is scored as a leader (the
classifier's probability ``p``) and its hypothetical group's ΔQ of eq. (4) is computed (what the
messages change in its members' values). The table says how many agents lead, how many groups
the messages would help (ΔQ > 0), how many the paper's min-max target would call leaders
(above 0.5 after min-max scaling over the same candidates), and whether ``p`` follows ΔQ: the
evidence for the leader-selection finding in docs/algorithm.md.

A group is always its leader and the ``k - 1`` nearest agents (``min(k, N)`` of them), so what
the leaders' choice changes is how the groups tie the fleet together: a second table counts the
distinct groups (member sets) each agent is in at the same formations (none: it hears nothing;
two or more: it bridges them) and its reach, the agents joined to it through shared groups (the
most its message can reach in one step). Two leaders with the same nearest agents make one
distinct group, so at N <= k every group is the whole fleet: one group, no bridge.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from udan.envs import EnvConfigError, make_vec

TIES = ("in no group", "in 1", "in 2", "in 3 or more", "mean reach", "reach: whole fleet")
COLUMNS = (
    "leading",
    "ΔQ > 0",
    "min-max target > 0.5",
    "mean ΔQ",
    "mean ΔQ of leaders",
    "mean ΔQ of others",
    "corr(p, ΔQ)",
)


@dataclass
class LeaderRow:
    """Leader statistics of one fleet size over every group formation of the episodes."""

    agents: int
    candidates: int
    """Agent-steps scored (present agents at group formations with a group of 2 or more)."""
    values: dict[str, float]
    ties: dict[str, float]
    """:data:`TIES`: shares of the present agent-steps at formations; mean reach in agents."""


def check_leaders(spec) -> None:
    """EnvConfigError unless the checkpoint has a leader classifier to inspect."""
    if not spec.communicates:
        raise EnvConfigError(f"--leaders: this {spec.algo} checkpoint has no leaders")


def group_ties(groups: np.ndarray, present: np.ndarray) -> np.ndarray:
    """Per present agent (slot order), a row of: how many distinct member sets of ``groups`` it
    is in, its reach (the agents joined to it through shared groups, itself included) and the
    number of agents present."""
    from udan.envs.grouping import communication_matrix

    n = len(present)
    groups = np.unique(np.sort(groups, axis=1), axis=0)
    reach = (communication_matrix(groups, n) | np.eye(n, dtype=bool)).astype(np.int64)
    while True:  # transitive closure: at most log2(N) squarings
        wider = (reach @ reach > 0).astype(np.int64)
        if (wider == reach).all():
            break
        reach = wider
    slots = np.flatnonzero(present)
    counts = np.bincount(groups.ravel(), minlength=n)[slots]
    return np.c_[counts, reach[np.ix_(slots, slots)].sum(axis=1), np.full_like(counts, slots.size)]


def collect(
    model, env_name: str, agents: int, obstacles, episodes: int, seed: int, **options
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(p, ΔQ) of every candidate leader at every group formation of greedy episodes, and the
    :func:`group_ties` rows of every present agent at the same formations, from the groups the
    actor formed (``options``: the task options the model was trained with)."""
    from udan.envs.grouping import neighbour_tables
    from udan.learner import Actor, hypothetical_delta_q, neighbour_rows

    check_leaders(model.spec)
    spec = model.spec
    env = make_vec(
        env_name, batch=episodes, seed=seed, agents=agents, obstacles=obstacles, **options
    )
    obs = env.reset()
    actor = Actor(model, env.batch, env.slots)
    probs, deltas, ties = [], [], []
    done = np.zeros(env.batch, dtype=bool)
    step = 0
    while not done.all():
        pos, present = env.pos.copy(), env.present.copy()
        actions = actor.act(obs, env.present, env.pos, env.joined)
        if step % spec.group_interval == 0:
            feats = actor.feats
            tables = neighbour_tables(pos, present, spec.attention_neighbours)
            rows, delta = hypothetical_delta_q(
                model, feats.view(env.batch, env.slots, -1), pos, present, tables
            )
            with torch.no_grad():
                logits = model.leader(feats, neighbour_rows(tables))[rows]
            probs.append(torch.sigmoid(logits).numpy())
            deltas.append(delta.numpy())
            ties += [group_ties(actor.groups[b], present[b]) for b in range(env.batch)]
        obs, _, done = env.step(actions)
        step += 1
    return np.concatenate(probs), np.concatenate(deltas), np.concatenate(ties)


def row(
    agents: int,
    prob: np.ndarray,
    delta: np.ndarray,
    threshold: float,
    ties: np.ndarray,
) -> LeaderRow:
    """The statistics of one fleet size's candidates, and of its agents' :func:`group_ties`
    rows (at least one)."""
    from udan.learner import leader_targets

    lead = prob > threshold
    minmax = leader_targets(torch.from_numpy(delta), "minmax").numpy()
    varied = len(delta) > 1 and prob.std() > 0 and delta.std() > 0
    values = {
        "leading": float(lead.mean()),
        "ΔQ > 0": float((delta > 0).mean()),
        "min-max target > 0.5": float((minmax > 0.5).mean()),
        "mean ΔQ": float(delta.mean()),
        "mean ΔQ of leaders": float(delta[lead].mean()) if lead.any() else float("nan"),
        "mean ΔQ of others": float(delta[~lead].mean()) if (~lead).any() else float("nan"),
        "corr(p, ΔQ)": float(np.corrcoef(prob, delta)[0, 1]) if varied else float("nan"),
    }
    counts, reach, fleet = ties.T
    shares = {
        "in no group": float((counts == 0).mean()),
        "in 1": float((counts == 1).mean()),
        "in 2": float((counts == 2).mean()),
        "in 3 or more": float((counts >= 3).mean()),
        "mean reach": float(reach.mean()),
        "reach: whole fleet": float((reach == fleet).mean()),
    }
    return LeaderRow(agents, len(delta), values, shares)


def leader_table(
    model,
    env_name: str,
    agents: tuple[int, int],
    obstacles,
    episodes: int,
    seed: int,
    **options,
) -> list[LeaderRow]:
    """One :class:`LeaderRow` per fleet size (obstacles drawn per episode from ``obstacles``)."""
    table = []
    for n in range(agents[0], agents[1] + 1):
        prob, delta, ties = collect(model, env_name, n, obstacles, episodes, seed, **options)
        if len(delta):
            table.append(row(n, prob, delta, model.spec.leader_threshold, ties))
    return table


def format_leaders(table: list[LeaderRow], title: str) -> str:
    """Markdown table: shares as percentages, ΔQ in the Q values' units."""
    lines = [
        f"**{title}**",
        "",
        "| agents | candidates | " + " | ".join(COLUMNS) + " |",
        "|---" * (len(COLUMNS) + 2) + "|",
    ]
    for r in table:
        cells = [
            "—"
            if np.isnan(r.values[c])
            else f"{100 * r.values[c]:.1f} %"
            if c in COLUMNS[:3]
            else f"{r.values[c]:+.3f}"
            for c in COLUMNS
        ]
        lines.append(f"| {r.agents} | {r.candidates} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "**The distinct groups each agent is in at the same formations, and its reach** (agents"
        " joined to it through shared groups, itself included: the most its message reaches in a"
        " step)",
        "",
        "| agents | " + " | ".join(TIES) + " |",
        "|---" * (len(TIES) + 1) + "|",
    ]
    for r in table:
        cells = [
            f"{r.ties[c]:.1f}" if c == "mean reach" else f"{100 * r.ties[c]:.1f} %" for c in TIES
        ]
        lines.append(f"| {r.agents} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
