"""A linear probe of UDAN's messages: do they carry where the hidden goal is?

For agents of ``arena/hidden_goal`` that cannot see the goal themselves, a ridge regression is
fitted on one set of episodes and scored (R^2) on another, from three inputs in turn: the
message the agent receives, its own feature ``l_i`` alone, and the message the same slot
received in another episode at the same step (shuffled: in distribution, about another goal).
The target is the goal's cell (row, column). An agent's own feature knows where the agent is and
where it has looked, so it can only rule cells out; a message that names the goal beats it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from udan.envs import EnvConfigError, make_vec

INPUTS = ("message", "own feature", "shuffled message")


@dataclass
class ProbeRow:
    """Held-out R^2 of each input at one fleet size."""

    agents: int
    samples: int
    """Agent-steps in the held-out set (agents not seeing the goal)."""
    r2: dict[str, float]


def ridge_fit(x: np.ndarray, y: np.ndarray, lam: float = 1e-2) -> tuple[np.ndarray, ...]:
    """Standardised ridge regression ``y ~ x``: (mean, scale, weights, bias) to predict with."""
    mean, scale = x.mean(0), x.std(0) + 1e-6
    z = (x - mean) / scale
    gram = z.T @ z + lam * len(z) * np.eye(z.shape[1])
    weights = np.linalg.solve(gram, z.T @ (y - y.mean(0)))
    return mean, scale, weights, y.mean(0)


def ridge_r2(fit: tuple[np.ndarray, ...], x: np.ndarray, y: np.ndarray) -> float:
    """Held-out R^2 of a :func:`ridge_fit`, averaged over the target's columns (<= 1; 0 is the
    mean's guess, below 0 worse than it)."""
    mean, scale, weights, bias = fit
    pred = (x - mean) / scale @ weights + bias
    residual = ((y - pred) ** 2).sum(0)
    total = ((y - y.mean(0)) ** 2).sum(0)
    return float(np.mean(1.0 - residual / np.maximum(total, 1e-12)))


def check_probe(spec, env_name: str, episodes: int) -> None:
    """EnvConfigError unless a model of ``spec`` on ``env_name`` can be probed over
    ``episodes`` episodes: it has messages, a hidden goal, and another episode to shuffle from."""
    if not spec.communicates:
        raise EnvConfigError(f"--probe: this {spec.algo} checkpoint has no messages to probe")
    if env_name != "arena/hidden_goal":
        raise EnvConfigError("--probe needs arena/hidden_goal (a goal the messages could carry)")
    if episodes < 2:
        raise EnvConfigError(
            "--probe needs at least 2 episodes (a shuffled message comes from another)"
        )


def collect(model, agents: int, episodes: int, seed: int) -> dict[str, np.ndarray]:
    """Roll out greedy episodes of ``arena/hidden_goal`` with ``agents`` agents and gather, for
    every agent-step where the agent does not see the goal, the three probe inputs and the
    goal's cell."""
    from udan.learner import Actor

    check_probe(model.spec, "arena/hidden_goal", episodes)
    env = make_vec("arena/hidden_goal", batch=episodes, seed=seed, agents=agents, obstacles=0)
    obs = env.reset()
    actor = Actor(model, env.batch, env.slots)
    other = np.roll(np.arange(env.batch), -1)  # episode b is shown episode b+1's messages
    rows: dict[str, list[np.ndarray]] = {name: [] for name in (*INPUTS, "goal")}
    done = np.zeros(env.batch, dtype=bool)
    while not done.all():
        actions = actor.act(obs, env.present, env.pos, env.joined)
        blind = env.present & ~env.in_zone()  # an agent sees the goal only in its zone
        message = actor.messages.view(env.batch, env.slots, -1).numpy()
        feats = actor.feats.view(env.batch, env.slots, -1).numpy()
        rows["message"].append(message[blind])
        rows["own feature"].append(feats[blind])
        rows["shuffled message"].append(message[other][blind])
        goal = np.broadcast_to(env.goal[:, None, :], env.pos.shape)
        rows["goal"].append(goal[blind].astype(np.float64))
        obs, _, done = env.step(actions)
    return {name: np.concatenate(parts) for name, parts in rows.items()}


def probe(model, agents: tuple[int, int], episodes: int, seed: int) -> list[ProbeRow]:
    """One :class:`ProbeRow` per fleet size: fitted on episodes of ``seed``, scored on others."""
    table = []
    for n in range(agents[0], agents[1] + 1):
        train = collect(model, n, episodes, seed)
        test = collect(model, n, episodes, seed + 1_000_003)
        r2 = {
            name: ridge_r2(ridge_fit(train[name], train["goal"]), test[name], test["goal"])
            for name in INPUTS
        }
        table.append(ProbeRow(n, len(test["goal"]), r2))
    return table


def format_probe(table: list[ProbeRow], title: str) -> str:
    """Markdown table: one row per fleet size, R^2 of each input."""
    lines = [
        f"**{title}**",
        "",
        "| agents | held-out agent-steps | " + " | ".join(f"R² {name}" for name in INPUTS) + " |",
        "|---" * (len(INPUTS) + 2) + "|",
    ]
    for row in table:
        values = " | ".join(f"{row.r2[name]:.3f}" for name in INPUTS)
        lines.append(f"| {row.agents} | {row.samples} | {values} |")
    return "\n".join(lines)
