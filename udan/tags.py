"""Does a checkpoint value the attacks that pay? The question behind pursuit's passive optimum.

Wolves act uniformly at random (as an ε-greedy rollout does early on) while the checkpoint reads
every step and says what each action is worth. Of the random attacks, those whose step paid
(reward above 0: a tag, the wolf's +1 against the attack's −0.2) are set against those that did
not: a learner that has learnt what a tag is worth rates an attack that is about to hit above
one that is not, and above the best move. Equal ratings mean the tags in its replay taught it
nothing yet, whatever the exploration brought in. For a learner trained on the team's reward,
the row also says how much of a change in Q_tot its mixer passes back to each agent's chosen Q
(VDN's sum: 1), the share of the team's TD error each wolf's Q is moved by.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from udan.envs import EnvConfigError, make_vec

#: Tasks whose agents attack.
ATTACKING = ("magent/pursuit", "magent/tiger")


@dataclass
class TagRow:
    """The random attacks of one fleet size, and what the checkpoint made of them."""

    agents: int
    attacks: int
    paid: int
    """Attacks whose step's reward was above 0."""
    q_paid: float
    """Mean Q the checkpoint gave the attacks that paid."""
    q_unpaid: float
    """Mean Q it gave the attacks that did not."""
    paid_greedy: float
    """Share of the paying attacks that were the checkpoint's own greedy action."""
    paid_above_moves: float
    """Share of the paying attacks rated above every move."""
    returned: float
    """The random wolves' summed episode returns (what the attacks and tags add up to)."""
    mixer_gradient: float
    """Mean ∂Q_tot/∂Q_i of the present agents' chosen Q (NaN where the model has no Q_tot: IQL,
    QMIX at another N or on another map than it mixes)."""


def check_tags(spec, env_name: str) -> None:
    """EnvConfigError unless a model of ``spec`` on ``env_name`` has Q values and attacks."""
    if spec.algo == "coma":
        raise EnvConfigError("--tags reads Q values; a coma checkpoint has a policy instead")
    if env_name not in ATTACKING:
        raise EnvConfigError(f"--tags needs a task whose agents attack ({', '.join(ATTACKING)})")


def tag_values(
    model, env_name: str, agents: tuple[int, int], episodes: int, seed: int, **options
) -> list[TagRow]:
    """One :class:`TagRow` per fleet size, ``episodes`` episodes of random wolves each."""
    from udan.learner import Actor

    check_tags(model.spec, env_name)
    table = []
    for n in range(agents[0], agents[1] + 1):
        env = make_vec(env_name, batch=episodes, seed=seed, agents=(n, n), **options)
        env.reset()
        attack = np.array([name.startswith("attack") for name in env.spec.actions])
        actor = Actor(model, env.batch, env.slots)
        rng = np.random.default_rng(seed)
        paid_q, unpaid_q, greedy, above, gradient = [], [], [], [], []
        mixes = _has_q_tot(model.spec, env)
        done = np.zeros(env.batch, dtype=bool)
        while not done.all():
            q = actor.values(env.observe(), env.present, env.pos, env.joined).numpy()
            q = q.reshape(env.batch, env.slots, -1)
            actions = rng.integers(0, len(attack), size=(env.batch, env.slots))
            attacked = attack[actions] & env.present
            chosen = np.take_along_axis(q, actions[..., None], -1)[..., 0]
            if mixes:
                gradient.append(_mixer_gradient(model, actor, env, chosen)[env.present])
            _, reward, done = env.step(actions)
            paid = attacked & (reward > 0)
            paid_q.append(chosen[paid])
            unpaid_q.append(chosen[attacked & ~paid])
            greedy.append((q.argmax(-1) == actions)[paid])
            above.append((chosen > q[..., ~attack].max(-1))[paid])
        paid_q, unpaid_q = np.concatenate(paid_q), np.concatenate(unpaid_q)
        table.append(
            TagRow(
                n,
                paid_q.size + unpaid_q.size,
                paid_q.size,
                _mean(paid_q),
                _mean(unpaid_q),
                _mean(np.concatenate(greedy)),
                _mean(np.concatenate(above)),
                float(env.episode_return.sum()),
                _mean(np.concatenate(gradient)) if gradient else float("nan"),
            )
        )
    return table


def _has_q_tot(spec, env) -> bool:
    """Whether the model mixes a Q_tot in ``env``: IQL never, QMIX only at the N and on the map
    (the global state's width) its hypernetwork was trained for."""
    if spec.algo == "qmix":
        width = env.global_state().shape[-1]
        return env.slots == spec.mix_agents and width == spec.state_dim
    return spec.algo != "iql"


def _mixer_gradient(model, actor, env, chosen: np.ndarray) -> np.ndarray:
    """∂Q_tot/∂Q_i (B, N) at this step: the mixer's weight on each agent's chosen Q."""
    import torch

    q = torch.from_numpy(chosen.astype(np.float32)).requires_grad_()
    state = env.global_state() if model.spec.state_dim else np.zeros((env.batch, 0))
    state = torch.from_numpy(state.astype(np.float32))
    feats = actor.feats.view(env.batch, env.slots, -1)
    with torch.enable_grad():
        total = model.mix(q, feats, state, torch.from_numpy(env.present)).sum()
        (grad,) = torch.autograd.grad(total, q)
    return grad.numpy()


def _mean(values: np.ndarray) -> float:
    """Mean of ``values``, NaN for none (no attack paid)."""
    return float(values.mean()) if values.size else float("nan")


def format_tags(table: list[TagRow], title: str) -> str:
    """Markdown table: one row per fleet size."""
    lines = [
        f"**{title}**",
        "",
        "| agents | random attacks | paid | Q of those that paid | Q of the others | "
        "paying attack greedy | paying attack above every move | ∂Q_tot/∂Q_i |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in table:
        shares = f"{100 * row.paid_greedy:.1f} % | {100 * row.paid_above_moves:.1f} %"
        mixer = "— (no Q_tot here)" if np.isnan(row.mixer_gradient) else f"{row.mixer_gradient:.3f}"
        lines.append(
            f"| {row.agents} | {row.attacks} | {row.paid} | {row.q_paid:+.3f} | "
            f"{row.q_unpaid:+.3f} | {shares} | {mixer} |"
        )
    return "\n".join(lines)
