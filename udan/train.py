"""``udan-train``: GCTDE training of UDAN (or a baseline) on any registered task, top to bottom.

Loop: roll out ``n_envs`` whole episodes at once with an epsilon-greedy :class:`Actor` (N drawn
per episode; groups formed every ``group_interval`` steps and stored as the paper's matrix C),
push them to an episode replay, then run ``updates_per_rollout`` updates on batches of whole
episodes: double-Q TD on Q_tot with a target network (eqs. 19-21) plus, for UDAN, the leader
classifier's BCE against min-max normalised ΔQ (eqs. 4-9). Checkpoints hold everything needed to
resume exactly (the replay sits beside them in ``replay.npz``). ``--calibrate`` measures a short
stretch of the planned run and prints its projected cost instead (:mod:`udan.budget`).
"""

from __future__ import annotations

import argparse
import ast
import copy
import csv
import dataclasses
import inspect
import itertools
import json
import sys
import time
import zipfile
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from torch.nn import functional as F

from udan.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from udan.envs import EnvConfigError, make_vec
from udan.envs.arena import ArenaBatch
from udan.envs.grouping import neighbour_tables
from udan.learner import (
    ALGOS,
    LEADER_TARGETS,
    Actor,
    ModelSpec,
    MultiAgentQ,
    hypothetical_delta_q,
    leader_targets,
    merge_rounds,
    neighbour_rows,
)
from udan.paths import FolderError, ensure_folder


@dataclass
class TrainConfig:
    """Every training choice; each field is a ``udan-train`` flag of the same name."""

    algo: str = "udan"
    """Learner: udan, qmix, vdn, iql or coma."""
    env: str = "arena/find_water"
    """Task to train on: an arena task or a MAgent scenario (magent/pursuit, tiger, queue)."""
    agents: str = "1-5"
    """Agents per episode, drawn uniformly from this range (baselines: a fixed count, e.g. 3)."""
    obstacles: str = "0-14"
    """Obstacles per episode, drawn uniformly from this range."""
    steps: float = 2e6
    """Environment steps to train for (one env of the batch stepping once is one step)."""
    max_steps: int = 0
    """Episode length in steps (0: the task's own: arena 50, pursuit and queue 300, tiger 200)."""
    map_size: int = 0
    """MAgent tasks: the map's side in cells (0: the scenario's own, the paper's)."""
    seed: int = 0
    """Seed of environments, exploration and weights."""
    out: str = "runs/default"
    """Run folder: checkpoint.pt, replay.npz, config.json, progress.csv, TensorBoard events."""
    n_envs: int = 16
    """Episodes rolled out in parallel per rollout."""
    batch_episodes: int = 32
    """Whole episodes per update batch."""
    updates_per_rollout: int = 4
    """Gradient updates after each rollout."""
    update_every: int = 1
    """Rollouts between two rounds of updates (1: after every rollout; more: fewer updates per
    episode, a cheaper-training deviation in docs/algorithm.md)."""
    bptt_steps: int = 0
    """Truncated backpropagation through time: gradients cross at most this many steps of the
    agents' LSTM (0: whole episodes; a cheaper-training deviation in docs/algorithm.md)."""
    buffer_episodes: int = 4000
    """Replay capacity in whole episodes."""
    lr: float = 5e-4
    """Adam learning rate."""
    gamma: float = 0.95
    """Discount factor (about a 20-step horizon: the arena is 9x9)."""
    eps_start: float = 1.0
    """Initial exploration rate."""
    eps_end: float = 0.05
    """Final exploration rate."""
    eps_fraction: float = 0.4
    """Fraction of training over which exploration decays linearly."""
    target_interval: int = 200
    """Updates between target-network copies."""
    grad_clip: float = 10.0
    """Gradient norm clip."""
    hidden: int = 64
    """Width of the agent network and its LSTM."""
    attn_dim: int = 32
    """Query/key width of the leader self-attention."""
    mix_dim: int = 32
    """Hidden width of the mixer."""
    group_size: int = 3
    """k: a leader and its k-1 nearest agents form a group."""
    group_interval: int = 5
    """T: steps between group formations."""
    leader_threshold: float = 0.5
    """Leader probability above which an agent leads a group."""
    leader_explore: float = 0.0
    """UDAN: chance that an agent the leader scorer passes over leads anyway in a training
    rollout, so groups, and gradients through the messages, exist before the scorer picks any."""
    mixer_init: str = "small"
    """UDAN: how its set mixer starts: small (output weights uniform in [0, 0.1)), or sum
    (Q_tot = the sum of the agents' Qs, VDN's mixer, from which training moves it)."""
    messages: str = "on"
    """UDAN: on, or off for the no-communication control (no leaders, groups or messages)."""
    explore: str = "uniform"
    """What ε's random actions are: uniform over every action (the paper), or balanced: a move
    or an attack with equal odds, then uniform among them (MAgent tasks, where a uniformly
    random pursuit wolf attacks on 12 of its 17 actions and hardly moves)."""
    shaping: float = 0.0
    """MAgent tasks: weight c of potential-based reward shaping, c·(γΦ(s')−Φ(s)) added to each
    agent's training reward, Φ its nearness to the closest opponent in view (pursuit, tiger) or
    the step cost of its walk to the nearest line (queue) (policy-invariant; scores and the
    logged return are the task's own; 0: none)."""
    prey_curriculum: str = ""
    """MAgent pursuit: START-END, shares of training: the sheep's alertness (the chance that a
    sheep seeing a wolf flees rather than wanders; 1 in the task) is 0 until START and rises
    linearly to 1 at END (one number F: 0-F; empty: the task's sheep throughout; a
    curriculum, docs/algorithm.md)."""
    leader_target: str = "signed"
    """UDAN: the leader classifier's target from ΔQ: signed (lead when messages raise the
    group's values) or minmax (the paper's eq. 9; runs older than this field used it)."""
    leader_coef: float = 1.0
    """Weight of the leader classifier's BCE loss."""
    td_lambda: float = 0.8
    """COMA: lambda of the critic's TD(lambda) targets (the COMA paper's and pymarl's 0.8)."""
    entropy_coef: float = 0.01
    """COMA: weight of the policy entropy bonus (as EPyMARL; without it the actor collapsed)."""
    checkpoint_every: float = 1e5
    """Environment steps between checkpoints (and at the end)."""
    torch_threads: int = 1
    """Intra-op threads for torch (1 is fastest for these small networks on 2 cores)."""
    workers: int = 0
    """Ray rollout workers, each playing n_envs episodes at a time while this process learns
    (0: everything in this one process, without Ray; docs/scaling.md)."""
    address: str = ""
    """Ray cluster the workers run on: ray://HOST:PORT, HOST:PORT or auto (empty: a local Ray
    started for this run; local: the workers in this process, without Ray)."""
    broadcast_every: int = 1
    """With workers: updates between two copies of the learner's weights sent to the workers
    (a rollout starts with the newest copy)."""


# A resumed run continues exactly when its config is unchanged; only these may differ (a longer
# --steps extends a finished run, with the exploration schedule stretched accordingly; checkpoints
# may come more or less often; a run with workers may go on with more, fewer or none, which
# is never exact: exact resume is a one-process promise).
RESUMABLE_FIELDS = {"steps", "out", "checkpoint_every", "workers", "address"}
# What a run whose config.json predates a field used for it, where that is not the default.
EARLIER_DEFAULTS = {"leader_target": "minmax"}


def field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings of a dataclass (the string under each field), for ``--help``."""
    tree = ast.parse(inspect.getsource(cls))
    body = tree.body[0].body
    docs = {}
    for prev, node in itertools.pairwise(body):
        if isinstance(prev, ast.AnnAssign) and isinstance(node, ast.Expr):
            docs[prev.target.id] = node.value.value
    return docs


# ---------------------------------------------------------------------------------- replay
class EpisodeReplay:
    """Ring buffer of whole episodes; observations as float16 (exact for the arena's values)."""

    #: How each field of an episode is stored.
    DTYPES: ClassVar[dict[str, type]] = {
        "obs": np.float16,
        "state": np.float16,
        "actions": np.int8,
        "rewards": np.float32,
        "present": np.bool_,
        "fresh": np.bool_,
        "pos": np.int16,
        "groups": np.int8,
    }

    def __init__(
        self, capacity: int, steps: int, slots: int, obs_dim: int, k: int, state_dim: int
    ) -> None:
        t1 = steps + 1
        self.capacity, self.size, self.next = capacity, 0, 0
        shapes = {
            "obs": (capacity, t1, slots, obs_dim),
            "state": (capacity, t1, state_dim),
            "actions": (capacity, steps, slots),
            "rewards": (capacity, steps, slots),
            "present": (capacity, t1, slots),
            "fresh": (capacity, t1, slots),
            "pos": (capacity, t1, slots, 2),
            "groups": (capacity, t1, slots, k),
        }
        self.data = {key: np.zeros(shape, self.DTYPES[key]) for key, shape in shapes.items()}
        self.data["groups"][...] = -1

    @classmethod
    def for_run(
        cls, cfg: TrainConfig, env: ArenaBatch, spec: ModelSpec, capacity: int = 0
    ) -> EpisodeReplay:
        """The replay of a run of ``cfg`` on ``env``'s task with networks of ``spec``, holding
        ``capacity`` episodes (default: ``cfg.buffer_episodes``)."""
        return cls(
            capacity or cfg.buffer_episodes,
            env.config.max_steps,
            env.slots,
            env.spec.size,
            cfg.group_size,
            spec.state_dim,
        )

    @classmethod
    def compact(cls, episodes: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``episodes`` as the replay stores them (what :meth:`add` would keep of them), so a
        rollout worker sends half the bytes."""
        return {key: value.astype(cls.DTYPES[key], copy=False) for key, value in episodes.items()}

    def add(self, episodes: dict[str, np.ndarray]) -> None:
        n = len(episodes["obs"])
        idx = (self.next + np.arange(n)) % self.capacity
        for key, value in episodes.items():
            self.data[key][idx] = value
        self.next = (self.next + n) % self.capacity
        self.size = min(self.size + n, self.capacity)

    def sample(self, n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        idx = rng.integers(0, self.size, size=n)
        return {key: value[idx] for key, value in self.data.items()}

    @staticmethod
    def pending(path: Path) -> Path:
        """Where :meth:`save` writes before the checkpoint of the same step exists."""
        return path.with_name(path.name + ".pending")

    def save(self, path: Path, steps: int) -> None:
        """Write the replay as it stands after ``steps`` environment steps to ``path``'s pending
        file; :meth:`commit` moves it in place once the checkpoint of those steps is written, so
        a run stopped at any moment of a save resumes from a replay and checkpoint of one step."""
        with self.pending(path).open("wb") as f:
            np.savez(f, steps=steps, size=self.size, next=self.next, **self.data)

    @classmethod
    def commit(cls, path: Path) -> None:
        cls.pending(path).replace(path)

    def load(self, path: Path, steps: int) -> None:
        """Restore the replay saved at ``steps``: the pending file when the run stopped between
        its checkpoint and the commit, else ``path``; :class:`CheckpointError` when neither is."""
        for candidate in (self.pending(path), path):
            try:
                with np.load(candidate) as f:
                    if int(f["steps"]) != steps:
                        continue
                    self.size, self.next = int(f["size"]), int(f["next"])
                    for key in self.data:
                        self.data[key][...] = f[key]
                    return
            except (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile):
                continue
        raise CheckpointError(
            f"{path}: no replay saved at the checkpoint's step {steps:,}, so the run cannot "
            "resume exactly"
        )


# ---------------------------------------------------------------------------------- rollout
def rollout(
    env: ArenaBatch, actor: Actor, epsilon: float, rng: np.random.Generator, with_state: bool
) -> dict[str, np.ndarray]:
    """Play one whole episode in every arena; returns arrays shaped (B, T(+1), ...)."""
    steps = env.config.max_steps
    obs = env.reset()
    actor.reset()
    rec: dict[str, list] = {
        k: [] for k in ("obs", "state", "actions", "rewards", "present", "fresh", "pos", "groups")
    }

    def record_observation() -> None:
        rec["obs"].append(obs)
        rec["state"].append(env.global_state() if with_state else np.zeros((env.batch, 0)))
        rec["present"].append(env.present.copy())
        rec["fresh"].append(env.joined.copy())
        rec["pos"].append(env.pos.copy())

    for _ in range(steps):
        record_observation()
        actions = actor.act(obs, env.present, env.pos, env.joined, epsilon, rng)
        rec["groups"].append(actor.padded_groups())
        rec["actions"].append(actions)
        obs, reward, _ = env.step(actions)
        rec["rewards"].append(reward)
    record_observation()
    rec["groups"].append(np.full_like(rec["groups"][-1], -1))
    return {k: np.stack(v, axis=1) for k, v in rec.items()}


def episode_returns(env: ArenaBatch, episodes: dict[str, np.ndarray]) -> np.ndarray:
    """Each episode's return per agent it started with (a MAgent game over leaves none present
    at its end), for the batch ``env`` that just played ``episodes``."""
    return env.episode_return.sum(1) / np.maximum(episodes["present"][:, 0].sum(1), 1)


def env_steps(env: ArenaBatch) -> int:
    """Environment steps of one rollout of ``env`` (every episode runs to the time limit)."""
    return env.batch * env.config.max_steps


class ShapedRewards:
    """A training batch whose rewards carry potential-based shaping (Ng, Harada & Russell,
    ICML 1999): ``r + c·(γ·Φ(s') − Φ(s))`` per agent, Φ the batch's ``potential()``.

    Summed over an episode the shaping telescopes to ``c·(γ^T Φ(s_T) − Φ(s_0))``, so it changes
    no policy's ranking, only how soon a learner meets the reward: on pursuit a uniformly random
    wolf scores no tag in a 300-step episode while its attacks cost −42 (docs/algorithm.md).
    Everything else, ``episode_return`` (what is logged) included, is the inner batch's.
    """

    def __init__(self, env: ArenaBatch, weight: float, gamma: float) -> None:
        self.env, self.weight, self.gamma = env, weight, gamma
        self._phi = np.zeros((env.batch, env.slots), dtype=np.float32)

    def __getattr__(self, name: str):
        return getattr(self.env, name)

    @property
    def prey_alertness(self) -> float:
        return self.env.prey_alertness

    @prey_alertness.setter
    def prey_alertness(self, value: float) -> None:  # a curriculum sets the inner batch's sheep
        self.env.prey_alertness = value

    def reset(self, where: np.ndarray | None = None) -> np.ndarray:
        obs = self.env.reset(where)
        self._phi = self.env.potential()
        return obs

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        acting = self.env.present.copy()
        obs, reward, done = self.env.step(actions)
        phi = self.env.potential()
        shaped = reward + self.weight * np.where(acting, self.gamma * phi - self._phi, 0.0)
        self._phi = phi
        return obs, shaped.astype(np.float32), done


def curriculum_span(text: str) -> tuple[float, float]:
    """``--prey-curriculum``'s START-END as shares of training (``F`` alone: 0-F; empty: no
    curriculum, (1, 1)); one-line refusal of anything else."""
    if not str(text).strip():
        return 1.0, 1.0
    try:
        parts = [float(p) for p in str(text).split("-")]
    except ValueError:
        parts = []
    if len(parts) == 1:
        parts = [0.0, *parts]
    if len(parts) != 2 or not 0.0 <= parts[0] < parts[1] <= 1.0:
        raise EnvConfigError(
            f"--prey-curriculum takes START-END (or END), shares of training with "
            f"0 <= START < END <= 1, not {text!r}"
        )
    return parts[0], parts[1]


def training_batch(cfg: TrainConfig, batch: int, seed) -> ArenaBatch:
    """The batch of ``cfg``'s task that rollouts play (shaped when ``cfg.shaping``)."""
    env = make_vec(
        cfg.env,
        batch=batch,
        seed=seed,
        agents=cfg.agents,
        obstacles=cfg.obstacles,
        **env_options(asdict(cfg)),
    )
    if cfg.shaping < 0:
        raise EnvConfigError(f"--shaping must be >= 0, got {cfg.shaping}")
    if cfg.shaping and not hasattr(env, "potential"):
        raise EnvConfigError(f"--shaping needs a MAgent task (a potential to shape), not {cfg.env}")
    curriculum_span(cfg.prey_curriculum)  # a bad span is refused here
    if cfg.prey_curriculum and cfg.env != "magent/pursuit":
        raise EnvConfigError(f"--prey-curriculum is for magent/pursuit, not {cfg.env}")
    if cfg.prey_curriculum and (cfg.workers or cfg.address):
        raise EnvConfigError("--prey-curriculum trains in one process: no --workers or --address")
    return ShapedRewards(env, cfg.shaping, cfg.gamma) if cfg.shaping else env


# ---------------------------------------------------------------------------------- update
def unroll(
    model: MultiAgentQ, obs: torch.Tensor, fresh: torch.Tensor, bptt_steps: int = 0
) -> torch.Tensor:
    """Agent features over whole episodes: obs (E, T1, N, D) -> (T1, E*N, H).

    With ``bptt_steps`` the episodes run in chunks of that many steps and the LSTM state passes
    from one chunk to the next detached: the same features, gradients truncated.
    """
    e, t1, n, d = obs.shape
    seq = obs.permute(1, 0, 2, 3).reshape(t1, e * n, d)
    new = fresh.permute(1, 0, 2).reshape(t1, e * n)
    state = model.encoder.initial_state(e * n)
    if bptt_steps == 0:
        return model.encoder(seq, state, new)[0]
    chunks = []
    for start in range(0, t1, bptt_steps):
        stop = start + bptt_steps
        feats, state = model.encoder(seq[start:stop], state, new[start:stop])
        state = (state[0].detach(), state[1].detach())
        chunks.append(feats)
    return torch.cat(chunks)


def stored_rounds(groups: np.ndarray) -> list[torch.Tensor]:
    """The acting-time groups (C) of a batch (E, T1, N, k) as rounds over (T1, E*N) rows."""
    e, t1, n, _ = groups.shape
    steps = groups.transpose(1, 0, 2, 3).reshape(t1 * e, n, -1)  # arena-steps, time-major
    counts = (steps >= 0).any(-1).sum(-1)  # Actor.padded_groups packs the groups first
    per_arena, offsets = [], []
    for a in np.flatnonzero(counts):
        rows = steps[a, : counts[a]]
        per_arena.append(rows[:, : int((rows[0] >= 0).sum())].astype(np.int64))
        offsets.append(int(a) * n)
    return merge_rounds(per_arena, offsets)


def q_values(model: MultiAgentQ, feats: torch.Tensor, rounds: list[torch.Tensor]) -> torch.Tensor:
    flat = feats.reshape(-1, feats.shape[-1])
    return model.head(flat, model.messages(flat, rounds)).view(*feats.shape[:2], -1)


def update(
    model: MultiAgentQ,
    target: MultiAgentQ,
    optim: torch.optim.Optimizer,
    batch: dict[str, np.ndarray],
    cfg: TrainConfig,
) -> dict[str, float]:
    """One gradient step on a batch of whole episodes; returns the losses."""
    e, t1, n = batch["present"].shape
    steps = t1 - 1
    obs = torch.from_numpy(batch["obs"].astype(np.float32))
    fresh = torch.from_numpy(batch["fresh"])
    present = torch.from_numpy(batch["present"]).permute(1, 0, 2)  # (T1, E, N)
    actions = torch.from_numpy(batch["actions"].astype(np.int64)).permute(1, 0, 2)
    rewards = torch.from_numpy(batch["rewards"]).permute(1, 0, 2)  # (T, E, N)
    state = torch.from_numpy(batch["state"].astype(np.float32)).permute(1, 0, 2)
    rounds = stored_rounds(batch["groups"]) if model.spec.communicates else []

    feats = unroll(model, obs, fresh, cfg.bptt_steps)  # (T1, E*N, H)
    q = q_values(model, feats, rounds).view(t1, e, n, -1)
    with torch.no_grad():
        target_feats = unroll(target, obs, fresh)
        target_q = q_values(target, target_feats, rounds).view(t1, e, n, -1)
        best_next = q[1:].argmax(-1, keepdim=True)  # double Q: online argmax, target value
        q_next = target_q[1:].gather(-1, best_next).squeeze(-1)  # (T, E, N)
    q_taken = q[:-1].gather(-1, actions.unsqueeze(-1)).squeeze(-1)
    # The time limit, which agents cannot observe, is bootstrapped through (Pardo et al., "Time
    # Limits in RL"), so a state's value does not depend on the clock. An agent that left (or
    # every agent, at a MAgent game over) has no next value; steps of an episode that is over
    # have no agent and are left out.
    alive, alive_next = present[:-1], present[1:]
    if model.spec.algo == "iql":
        y = rewards + cfg.gamma * q_next.masked_fill(~alive_next, 0.0)
        td_loss = ((q_taken - y)[alive] ** 2).mean()
    else:
        h = feats.shape[-1]
        feats_t = feats.view(t1, e, n, h)
        q_tot = model.mix(
            q_taken.reshape(-1, n),
            feats_t[:-1].reshape(-1, n, h),
            state[:-1].reshape(steps * e, -1),
            alive.reshape(-1, n),
        )
        with torch.no_grad():
            next_feats = target_feats.view(t1, e, n, h)[1:]
            next_tot = target.mix(
                q_next.reshape(-1, n),
                next_feats.reshape(-1, n, h),
                state[1:].reshape(steps * e, -1),
                alive_next.reshape(-1, n),
            )
        continuing = alive_next.any(-1).reshape(-1)
        y = rewards.sum(-1).reshape(-1) + cfg.gamma * torch.where(continuing, next_tot, 0.0)
        acting = alive.any(-1).reshape(-1)
        td_loss = F.mse_loss(q_tot[acting], y[acting])
    loss = td_loss
    losses = {"td_loss": td_loss.item()}
    if model.spec.communicates:
        formed = torch.arange(0, t1, model.spec.group_interval)
        f = feats.view(t1, e, n, -1)[formed].reshape(len(formed) * e * n, -1).detach()
        pos = batch["pos"][:, formed.numpy()].transpose(1, 0, 2, 3).reshape(-1, n, 2)
        alive_f = batch["present"][:, formed.numpy()].transpose(1, 0, 2).reshape(-1, n)
        count = model.spec.attention_neighbours  # one neighbour search serves both uses
        tables = neighbour_tables(pos, alive_f, count)
        rows, delta = hypothetical_delta_q(model, f.view(-1, n, f.shape[-1]), pos, alive_f, tables)
        if len(rows):
            logits = model.leader(f, neighbour_rows(tables))[rows]
            target = leader_targets(delta, cfg.leader_target)
            leader_loss = F.binary_cross_entropy_with_logits(logits, target)
            loss = loss + cfg.leader_coef * leader_loss
            losses["leader_loss"] = leader_loss.item()
    optim.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
    optim.step()
    return losses


def update_round(
    model: MultiAgentQ,
    target: MultiAgentQ,
    optim: torch.optim.Optimizer,
    replay: EpisodeReplay,
    run: Run,
    interrupted: Callable[[], bool] = lambda: False,
) -> dict[str, float]:
    """The updates the rollout just added to ``replay`` earns: ``updates_per_rollout`` after
    every ``update_every``-th rollout once the replay holds a batch (fewer if ``interrupted()``
    turns true); the target network copied every ``target_interval`` updates. Returns the last
    update's losses (none if no update ran)."""
    cfg, progress = run.cfg, run.progress
    losses: dict[str, float] = {}
    rollouts = progress["episodes"] // cfg.n_envs + 1
    if replay.size < cfg.batch_episodes or rollouts % cfg.update_every:
        return losses
    for _ in range(cfg.updates_per_rollout):
        if interrupted():
            break
        losses = update(model, target, optim, replay.sample(cfg.batch_episodes, run.rng), cfg)
        progress["updates"] += 1
        if progress["updates"] % cfg.target_interval == 0:
            target.load_state_dict(model.state_dict())
    return losses


# ---------------------------------------------------------------------------------- main loop
def env_options(config: dict) -> dict:
    """The task options of a run's config (a ``TrainConfig`` as a dict) beyond agents and
    obstacles: what ``udan-eval`` must pass to meet the same task."""
    options = {key: config.get(key, 0) for key in ("max_steps", "map_size")}
    return {key: value for key, value in options.items() if value}


def build(cfg: TrainConfig) -> tuple[ArenaBatch, MultiAgentQ]:
    """The environment batch and a fresh model for ``cfg`` (validates algo, env and options)."""
    if cfg.algo not in ALGOS:
        raise EnvConfigError(f"unknown algo {cfg.algo!r}; known: {', '.join(ALGOS)}")
    if cfg.update_every < 1 or cfg.bptt_steps < 0:
        raise EnvConfigError("--update-every must be >= 1 and --bptt-steps >= 0")
    if cfg.map_size and not cfg.env.startswith("magent/"):
        raise EnvConfigError(f"--map-size is for MAgent tasks, not {cfg.env}")
    env = training_batch(cfg, cfg.n_envs, cfg.seed)
    if cfg.messages not in ("on", "off"):
        raise EnvConfigError(f"--messages must be on or off, not {cfg.messages!r}")
    if not 0.0 <= cfg.leader_explore <= 1.0:
        raise EnvConfigError(f"--leader-explore {cfg.leader_explore} is not a probability")
    if cfg.explore not in EXPLORE:
        raise EnvConfigError(f"--explore must be one of {', '.join(EXPLORE)}, not {cfg.explore!r}")
    if cfg.explore == "balanced" and (cfg.algo == "coma" or not getattr(env.spec, "n_attacks", 0)):
        raise EnvConfigError(
            "--explore balanced is for value learners on tasks with attacks (MAgent), "
            f"not {cfg.algo} on {cfg.env}"
        )
    if cfg.leader_target not in LEADER_TARGETS:
        raise EnvConfigError(
            f"--leader-target must be one of {', '.join(LEADER_TARGETS)}, not {cfg.leader_target!r}"
        )
    if cfg.mixer_init not in MIXER_INITS:
        raise EnvConfigError(
            f"--mixer-init must be one of {', '.join(MIXER_INITS)}, not {cfg.mixer_init!r}"
        )
    if cfg.mixer_init != "small" and cfg.algo != "udan":
        raise EnvConfigError(f"--mixer-init is for udan's set mixer; {cfg.algo} has none")
    if cfg.messages == "off" and cfg.algo != "udan":
        raise EnvConfigError(f"--messages off is for udan; {cfg.algo} has no messages")
    if cfg.algo == "qmix" and env.config.agents[0] != env.config.agents[1]:
        raise EnvConfigError("qmix mixes a fixed number of agents: give --agents a single count")
    spec = ModelSpec(
        algo=cfg.algo,
        obs_dim=env.spec.size,
        n_actions=len(env.spec.actions),
        hidden=cfg.hidden,
        attn_dim=cfg.attn_dim,
        mix_dim=cfg.mix_dim,
        group_size=cfg.group_size,
        group_interval=cfg.group_interval,
        leader_threshold=cfg.leader_threshold,
        state_dim=env.global_state().shape[1] if cfg.algo == "qmix" else 0,
        mix_agents=env.slots if cfg.algo == "qmix" else 0,
        messages=cfg.messages == "on",
    )
    torch.manual_seed(cfg.seed)
    model = MultiAgentQ(spec)
    if cfg.mixer_init == "sum":
        model.mixer.start_as_sum()
    return env, model


#: ``TrainConfig.mixer_init``'s choices.
MIXER_INITS = ("small", "sum")

#: ``TrainConfig.explore``'s choices.
EXPLORE = ("uniform", "balanced")

#: The logged training return is the mean of the last this many episodes.
RETURN_WINDOW = 200


def training_actor(cfg: TrainConfig, model: MultiAgentQ, env: ArenaBatch) -> Actor:
    """The acting side of a training rollout: ``cfg``'s leader exploration and the distribution
    of its ε's random actions (:attr:`TrainConfig.explore`)."""
    actor = Actor(model, env.batch, env.slots)
    actor.leader_explore = cfg.leader_explore
    if cfg.explore == "balanced":
        moves, attacks = env.spec.n_moves, env.spec.n_attacks
        actor.random_actions = np.r_[np.full(moves, 0.5 / moves), np.full(attacks, 0.5 / attacks)]
    return actor


class Run:
    """A run folder's bookkeeping, shared by every learner's loop.

    Checks the config on resume and restores progress and every random state (the caller
    restores its networks from :attr:`checkpoint`), keeps the exploration schedule, writes
    ``config.json``, ``progress.csv``, TensorBoard scalars and the one-line progress print, and
    says when a checkpoint is due.
    """

    def __init__(
        self,
        cfg: TrainConfig,
        env: ArenaBatch,
        resume: bool,
        loss_names: tuple[str, ...],
        log=print,
    ) -> None:
        self.cfg, self.env, self.log, self.loss_names = cfg, env, log, loss_names
        self.out = Path(cfg.out)
        self.path = self.out / "checkpoint.pt"
        self.rng = np.random.default_rng(cfg.seed)
        self.progress = {"steps": 0, "episodes": 0, "updates": 0, "seconds": 0.0}
        self.checkpoint: dict | None = None
        if resume:
            ckpt = load_checkpoint(self.path)
            defaults = asdict(TrainConfig()) | EARLIER_DEFAULTS  # fields newer than the run
            diff = sorted(
                k
                for k, v in asdict(cfg).items()
                if k not in RESUMABLE_FIELDS and ckpt["config"].get(k, defaults[k]) != v
            )
            if diff:
                raise CheckpointError(
                    f"--resume: config differs from the run's in {', '.join(diff)}"
                )
            self.progress = ckpt["progress"]
            self.rng.bit_generator.state = ckpt["rng"]["train"]
            env.rng.bit_generator.state = ckpt["rng"]["env"]
            torch.set_rng_state(ckpt["rng"]["torch"])
            self.checkpoint = ckpt
        else:
            self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "config.json").write_text(json.dumps(asdict(cfg), indent=2))
        self.writer = _tensorboard(self.out)
        self.csv_file = self._progress_file()
        self.csv = csv.writer(self.csv_file)
        if self.progress["steps"] == 0:
            self.csv.writerow(
                ["steps", "episodes", "updates", "epsilon", "return", *loss_names, "steps_per_s"]
            )
        # the episodes the logged return averages, kept in the checkpoint so that a resumed
        # run's curve goes on as the uninterrupted run's would (checkpoints older than this
        # keep none: their resumed curves restart the average)
        self.returns: list[float] = list(self.progress.pop("recent_returns", []))
        self.next_checkpoint = self.progress["steps"] + cfg.checkpoint_every
        self.started, self.steps_at_start = time.perf_counter(), self.progress["steps"]
        self.seconds_before = self.progress["seconds"]

    def _progress_file(self):
        """progress.csv opened for this run's rows: a new run starts it afresh (a run that died
        before its first checkpoint leaves one behind), a resumed run drops the rows written
        after its checkpoint, which it plays again."""
        path = self.out / "progress.csv"
        if self.progress["steps"] == 0 or not path.is_file():
            return path.open("w", newline="")
        with path.open(newline="") as f:
            rows = list(csv.reader(f))
        kept = rows[:1] + [r for r in rows[1:] if r and int(r[0]) <= self.progress["steps"]]
        with path.open("w", newline="") as f:
            csv.writer(f).writerows(kept)
        return path.open("a", newline="")

    @property
    def running(self) -> bool:
        return self.progress["steps"] < self.cfg.steps

    def epsilon(self, at_steps: int | None = None) -> float:
        """Linear decay from eps_start to eps_end over eps_fraction of the run, at ``at_steps``
        (default: the steps played so far)."""
        cfg = self.cfg
        frac = self._ramp(0.0, cfg.eps_fraction, at_steps)
        return cfg.eps_start + frac * (cfg.eps_end - cfg.eps_start)

    def prey_alertness(self) -> float:
        """The sheep's alertness for the next rollout: 1 (the task's) unless ``prey_curriculum``
        holds it at 0 until its START and has it rise linearly to 1 at its END."""
        if not self.cfg.prey_curriculum:
            return 1.0
        return self._ramp(*curriculum_span(self.cfg.prey_curriculum))

    def _ramp(self, start: float, end: float, at_steps: int | None = None) -> float:
        """0 until ``start`` of the run, rising linearly to 1 at ``end``, at ``at_steps``
        (default: the steps played so far); 1 from there on."""
        steps = self.progress["steps"] if at_steps is None else at_steps
        total = self.cfg.steps
        return min(max(steps - start * total, 0) / max((end - start) * total, 1), 1.0)

    def before_rollout(self, env: ArenaBatch) -> None:
        """Set what the schedule gives the next rollout's task: pursuit's sheep, under a
        ``prey_curriculum``."""
        if self.cfg.prey_curriculum:
            env.prey_alertness = self.prey_alertness()

    def record(
        self,
        epsilon: float,
        losses: dict[str, float],
        returns: np.ndarray,
        steps: int,
        worker_rates: dict[str, float] | None = None,
    ) -> bool:
        """Account for a rollout of ``steps`` environment steps whose episodes returned
        ``returns`` (:func:`episode_returns`) and log it; True when a checkpoint is due.
        ``worker_rates``: each rollout worker's own steps per second, for the log."""
        progress = self.progress
        alertness = self.prey_alertness()  # the rollout's, read before its steps are counted
        self.returns = (self.returns + returns.tolist())[-RETURN_WINDOW:]
        progress["steps"] += steps
        progress["episodes"] += len(returns)
        rate = (progress["steps"] - self.steps_at_start) / (time.perf_counter() - self.started)
        mean_return = float(np.mean(self.returns))
        self.csv.writerow(
            [
                progress["steps"],
                progress["episodes"],
                progress["updates"],
                f"{epsilon:.3f}",
                f"{mean_return:.3f}",
                *(f"{losses.get(k, float('nan')):.4f}" for k in self.loss_names),
                f"{rate:.0f}",
            ]
        )
        self.csv_file.flush()  # a run is watched while it trains
        worker_rates = worker_rates or {}
        if self.writer is not None:
            for key, value in {
                "return": mean_return,
                "epsilon": epsilon,
                "steps_per_s": rate,
                **({"prey_alertness": alertness} if self.cfg.prey_curriculum else {}),
                **losses,
            }.items():
                self.writer.add_scalar(f"train/{key}", value, progress["steps"])
            for name, value in worker_rates.items():
                self.writer.add_scalar(f"workers/{name}_steps_per_s", value, progress["steps"])
        per_worker = " (" + ", ".join(f"{n} {v:,.0f}" for n, v in worker_rates.items()) + ")"
        self.log(
            f"\r[{self.cfg.algo}] {progress['steps'] / self.cfg.steps:6.1%} steps "
            f"{progress['steps']:,} return {mean_return:6.2f} eps {epsilon:.2f} "
            f"{f'alertness {alertness:.2f} ' if self.cfg.prey_curriculum else ''}"
            f"{rate:,.0f} steps/s{per_worker if worker_rates else ''}",
            end="",
        )
        due = progress["steps"] >= self.next_checkpoint or not self.running
        if due:
            self.next_checkpoint = progress["steps"] + self.cfg.checkpoint_every
        return due

    def save(
        self,
        model: MultiAgentQ,
        target: MultiAgentQ | None,
        optim: torch.optim.Optimizer,
        replay: EpisodeReplay | None = None,
        extra: dict | None = None,
    ) -> None:
        """Write the checkpoint, and ``replay`` beside it (value learners) so that a stop at any
        moment leaves a pair of one step."""
        self.progress["seconds"] = self.seconds_before + time.perf_counter() - self.started
        rng_state = {
            "train": self.rng.bit_generator.state,
            "env": self.env.rng.bit_generator.state,
            "torch": torch.get_rng_state(),
        }
        replay_path = self.out / "replay.npz"
        if replay is not None:
            replay.save(replay_path, self.progress["steps"])
        progress = {**self.progress, "recent_returns": list(self.returns)}
        save_checkpoint(
            self.path, model, target, optim, self.cfg, self.env, progress, rng_state, extra
        )
        if replay is not None:
            EpisodeReplay.commit(replay_path)

    def restore(
        self,
        model: MultiAgentQ,
        target: MultiAgentQ,
        optim: torch.optim.Optimizer,
        replay: EpisodeReplay,
    ) -> None:
        """A value learner's networks, optimiser and replay as the resumed checkpoint left them."""
        if self.checkpoint is None:
            return
        model.load_state_dict(self.checkpoint["weights"])
        target.load_state_dict(self.checkpoint["target_weights"])
        optim.load_state_dict(self.checkpoint["optimizer"])
        replay.load(self.out / "replay.npz", self.progress["steps"])

    def close(self) -> Path:
        self.log("")
        self.csv_file.close()
        if self.writer is not None:
            self.writer.close()
        return self.path


def train(cfg: TrainConfig, resume: bool = False, log=print) -> Path:
    """Train until ``cfg.steps``; returns the checkpoint path."""
    if cfg.workers or cfg.address:  # rollouts on workers (udan.distributed), maybe over Ray
        from udan.distributed import train_with_workers

        return train_with_workers(cfg, resume=resume, log=log)
    if cfg.algo == "coma":  # on-policy actor-critic: its own loop, same config and checkpoint
        from udan.coma import train_coma

        return train_coma(cfg, resume=resume, log=log)
    torch.set_num_threads(cfg.torch_threads)
    env, model = build(cfg)
    target = copy.deepcopy(model)
    optim = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    replay = EpisodeReplay.for_run(cfg, env, model.spec)
    run = Run(cfg, env, resume, ("td_loss", "leader_loss"), log)
    run.restore(model, target, optim, replay)
    actor = training_actor(cfg, model, env)
    while run.running:
        epsilon = run.epsilon()
        run.before_rollout(env)
        episodes = rollout(env, actor, epsilon, run.rng, with_state=model.spec.state_dim > 0)
        replay.add(episodes)
        losses = update_round(model, target, optim, replay, run)
        if run.record(epsilon, losses, episode_returns(env, episodes), env_steps(env)):
            run.save(model, target, optim, replay)
    return run.close()


def _tensorboard(out: Path):
    """A TensorBoard writer when tensorboard is installed (it is, with the ``train`` extra)."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(log_dir=str(out / "tb"))


def main(argv: list[str] | None = None) -> int:
    docs = field_docs(TrainConfig)
    parser = argparse.ArgumentParser(prog="udan-train", description=__doc__.splitlines()[0])
    for f in dataclasses.fields(TrainConfig):
        kind = float if f.type in ("float", float) else int if f.type in ("int", int) else str
        parser.add_argument(
            f"--{f.name.replace('_', '-')}",
            dest=f.name,
            type=kind,
            default=f.default,
            help=f"{docs.get(f.name, '')} (default: %(default)s)",
        )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --out exactly where its checkpoint left off",
    )
    parser.add_argument(
        "--calibrate",
        action="store_true",
        help="measure a short stretch of this run and print its projected cost (JSON and one "
        "line) instead of training",
    )
    args = vars(parser.parse_args(argv))
    resume, calibrating = args.pop("resume"), args.pop("calibrate")
    from udan.cluster import ScaleError  # Ray itself is imported only for workers

    cfg = TrainConfig(**args)
    try:
        if calibrating:
            from udan.budget import calibrate, summary

            budget = calibrate(cfg)
            print(json.dumps(budget, indent=1))
            print(summary(budget))
            return 0
        if not resume and (Path(cfg.out) / "checkpoint.pt").exists():
            raise CheckpointError(f"{cfg.out} already holds a run; use --resume or another --out")
        if resume and not (Path(cfg.out) / "checkpoint.pt").exists():
            raise CheckpointError(f"--resume: {cfg.out} holds no checkpoint.pt")
        ensure_folder(cfg.out, "--out")
        path = train(cfg, resume=resume, log=lambda *a, **k: print(*a, **k, flush=True))
    except (EnvConfigError, CheckpointError, FolderError, ScaleError) as err:
        print(f"udan-train: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as stop:
        said = str(stop) or "the last checkpoint is kept"
        print(f"\nudan-train: interrupted; {said}", file=sys.stderr)
        return 130
    print(f"checkpoint: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
