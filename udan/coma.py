"""COMA (Foerster et al. 2018, "Counterfactual Multi-Agent Policy Gradients"), a paper baseline.

On-policy actor-critic at a fixed N, top to bottom: roll out ``n_envs`` whole episodes sampling
from the shared actor's softmax (an epsilon floor annealed like the value learners' exploration),
fit a centralised critic ``Q(s, u_-a, o_a, a)`` to TD(lambda) returns of the team reward against
a target critic, then step the actor along ``A_a = Q(s, u) - sum_u' pi(u'|tau_a) Q(s, (u_-a, u'))``.

The actor is :class:`udan.learner.MultiAgentQ` with ``algo="coma"`` (encoder + LSTM + head, whose
outputs are policy logits), so acting, ``udan-eval`` and export need nothing else and work at any
N; only the critic is tied to the N it was trained at. Of :class:`udan.train.TrainConfig` COMA
uses ``n_envs`` (episodes per update), ``updates_per_rollout`` (critic steps per rollout), ``lr``,
``gamma``, ``eps_*``, ``target_interval`` (in critic steps), ``grad_clip`` and ``hidden`` (actor and
critic width); the replay fields do not apply to an on-policy learner.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from udan.envs import EnvConfigError
from udan.learner import Actor
from udan.train import (
    Run,
    TrainConfig,
    build,
    env_steps,
    episode_returns,
    q_values,
    rollout,
    unroll,
)


class Critic(nn.Module):
    """Q(s, u_-a, o_a, a) for each own action of agent a: one row per agent gives the baseline.

    Inputs per agent: the global state, its own observation, the other agents' actions one-hot
    (its own slot zeroed, so the row is a function of its own action only) and its id one-hot.
    """

    def __init__(
        self, state_dim: int, obs_dim: int, n_agents: int, n_actions: int, hidden: int
    ) -> None:
        super().__init__()
        self.n_agents, self.n_actions = n_agents, n_actions
        self.net = nn.Sequential(
            nn.Linear(state_dim + obs_dim + n_agents * n_actions + n_agents, hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
            nn.Linear(hidden, n_actions),
        )

    def forward(
        self, state: torch.Tensor, obs: torch.Tensor, actions: torch.Tensor
    ) -> torch.Tensor:
        """``state`` (..., S), ``obs`` (..., N, D), ``actions`` (..., N) -> Q (..., N, U)."""
        n = self.n_agents
        others = ~torch.eye(n, dtype=torch.bool)  # row a: every slot but a
        joint = F.one_hot(actions, self.n_actions).to(obs.dtype)  # (..., N, U)
        joint = (joint.unsqueeze(-3) * others[..., None]).flatten(-2)  # (..., N, N*U)
        ids = torch.eye(n).expand(*obs.shape[:-1], n)
        state = state.unsqueeze(-2).expand(*obs.shape[:-1], state.shape[-1])
        return self.net(torch.cat([state, obs, joint, ids], dim=-1))


def policy(logits: torch.Tensor, epsilon: float) -> torch.Tensor:
    """The behaviour policy: softmax mixed with a uniform floor of total mass ``epsilon``."""
    return (1 - epsilon) * torch.softmax(logits, -1) + epsilon / logits.shape[-1]


def td_lambda_targets(
    rewards: torch.Tensor, q_next: torch.Tensor, gamma: float, lam: float
) -> torch.Tensor:
    """TD(lambda) returns (T, ...) from rewards (T, ...) and target Q of the next steps (T, ...).

    Episodes end only at the time limit, which nobody observes: the last step bootstraps on the
    target Q of the action sampled at the final observation (as the value learners do).
    """
    targets = torch.empty_like(q_next)
    ret = q_next[-1]
    for t in reversed(range(len(rewards))):
        ret = rewards[t] + gamma * ((1 - lam) * q_next[t] + lam * ret)
        targets[t] = ret
    return targets


def counterfactual_advantage(
    q: torch.Tensor, pi: torch.Tensor, actions: torch.Tensor
) -> torch.Tensor:
    """A_a = Q(s, u) - sum_u' pi(u'|tau_a) Q(s, (u_-a, u')); q, pi (..., U), actions (...)."""
    return q.gather(-1, actions.unsqueeze(-1)).squeeze(-1) - (pi * q).sum(-1)


class SamplingActor(Actor):
    """:class:`Actor` that samples from :func:`policy` instead of acting epsilon-greedily."""

    def act(
        self,
        obs: np.ndarray,
        present: np.ndarray,
        pos: np.ndarray,
        fresh: np.ndarray,
        epsilon: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        probs = policy(self.values(obs, present, pos, fresh), epsilon).numpy()
        draw = rng.random((len(probs), 1))
        actions = (probs.cumsum(-1) < draw).sum(-1).clip(max=probs.shape[-1] - 1)
        return actions.reshape(self.batch, self.slots)


def train_coma(cfg: TrainConfig, resume: bool = False, log: Callable = print) -> Path:
    """Train COMA until ``cfg.steps``; returns the checkpoint path (run folder as udan-train's)."""
    torch.set_num_threads(cfg.torch_threads)
    env, model = build(cfg)
    if env.config.agents[0] != env.config.agents[1]:
        raise EnvConfigError("coma's critic takes a fixed number of agents: give --agents a count")
    n, n_actions = env.slots, model.spec.n_actions
    critic = Critic(env.global_state().shape[1], env.spec.size, n, n_actions, cfg.hidden)
    target_critic = Critic(env.global_state().shape[1], env.spec.size, n, n_actions, cfg.hidden)
    target_critic.load_state_dict(critic.state_dict())
    optim = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    critic_optim = torch.optim.Adam(critic.parameters(), lr=cfg.lr)
    run = Run(cfg, env, resume, ("critic_loss", "actor_loss"), log)
    if run.checkpoint is not None:
        model.load_state_dict(run.checkpoint["weights"])
        optim.load_state_dict(run.checkpoint["optimizer"])
        critic.load_state_dict(run.checkpoint["critic_weights"])
        target_critic.load_state_dict(run.checkpoint["critic_target_weights"])
        critic_optim.load_state_dict(run.checkpoint["critic_optimizer"])
    actor = SamplingActor(model, env.batch, n)
    progress, rng = run.progress, run.rng
    while run.running:
        epsilon = run.epsilon()
        run.before_rollout(env)
        episodes = rollout(env, actor, epsilon, rng, with_state=True)
        # one more draw at the final observation: the action the last TD target bootstraps on
        final = actor.act(env.observe(), env.present, env.pos, env.joined, epsilon, rng)

        # time-major tensors: obs (T1, E, N, D), state (T1, E, S), actions (T1, E, N)
        obs = torch.from_numpy(episodes["obs"]).permute(1, 0, 2, 3)
        state = torch.from_numpy(episodes["state"]).permute(1, 0, 2)
        actions = torch.from_numpy(np.concatenate([episodes["actions"], final[:, None]], 1))
        actions = actions.long().permute(1, 0, 2)
        team_reward = torch.from_numpy(episodes["rewards"]).sum(-1).T  # (T, E)

        # critic: TD(lambda) on Q of the taken joint action, targets from the target critic
        with torch.no_grad():
            q_target = target_critic(state, obs, actions).gather(-1, actions[..., None])[..., 0]
            y = td_lambda_targets(team_reward[..., None], q_target[1:], cfg.gamma, cfg.td_lambda)
        for _ in range(cfg.updates_per_rollout):
            q_taken = critic(state[:-1], obs[:-1], actions[:-1]).gather(-1, actions[:-1, ..., None])
            critic_loss = F.mse_loss(q_taken[..., 0], y)
            critic_optim.zero_grad()
            critic_loss.backward()
            torch.nn.utils.clip_grad_norm_(critic.parameters(), cfg.grad_clip)
            critic_optim.step()
            progress["updates"] += 1
            if progress["updates"] % cfg.target_interval == 0:
                target_critic.load_state_dict(critic.state_dict())

        # actor: policy gradient with the counterfactual baseline of the updated critic
        feats = unroll(
            model, torch.from_numpy(episodes["obs"]), torch.from_numpy(episodes["fresh"])
        )
        t1, e = obs.shape[:2]
        logits = q_values(model, feats, []).view(t1, e, n, n_actions)[:-1]
        pi = policy(logits, epsilon)
        with torch.no_grad():
            q_all = critic(state[:-1], obs[:-1], actions[:-1])
            advantage = counterfactual_advantage(q_all, pi, actions[:-1])
        log_pi = pi.gather(-1, actions[:-1, ..., None])[..., 0].log()
        entropy = -(logits.softmax(-1) * logits.log_softmax(-1)).sum(-1).mean()
        actor_loss = -(advantage * log_pi).mean() - cfg.entropy_coef * entropy
        optim.zero_grad()
        actor_loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        optim.step()

        losses = {"critic_loss": critic_loss.item(), "actor_loss": actor_loss.item()}
        if run.record(epsilon, losses, episode_returns(env, episodes), env_steps(env)):
            extra = {
                "critic_weights": critic.state_dict(),
                "critic_target_weights": target_critic.state_dict(),
                "critic_optimizer": critic_optim.state_dict(),
            }
            run.save(model, None, optim, extra=extra)
    return run.close()
