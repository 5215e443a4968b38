"""Rollout workers and one learner: the exchange behind ``udan-train --workers N``, Ray aside.

Each worker (:class:`RolloutWorker`) owns ``n_envs`` environments and a copy of the acting
network. Asked for a rollout with the learner's weights and an exploration rate, it plays
``n_envs`` whole episodes and sends them back as the replay stores them (:class:`Rollout`).
The learner (:func:`train_with_workers`) keeps every worker busy: when a rollout arrives it asks
that worker for the next one at once, then adds the episodes to its replay and runs the updates
one process would run for them (``updates_per_rollout`` every ``update_every`` rollouts). So
updates per episode, replay, checkpoints and logs are as in one process; what differs is that a
rollout acts with weights some rounds of updates older (up to one round per worker), and that
the order in which rollouts arrive makes a run with workers not exactly reproducible.

A pool (:class:`WorkerPool`) carries requests and rollouts. Backends are registered by name,
Ray imported only when its pool is made: ``local`` plays the requests in this process, one after
the other (the fast tests; debugging without Ray); ``ray`` runs each worker as a Ray actor
(:mod:`udan.cluster` starts or joins Ray). A worker that dies is replaced by a new one with
seeds of its own; its unfinished rollout is lost, never counted, and the learner refuses any
rollout it has already counted.
"""

from __future__ import annotations

import copy
import dataclasses
import signal
import time
from collections import deque
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from udan.cluster import ScaleError, import_ray, ray_session
from udan.envs import EnvConfigError
from udan.learner import ModelSpec, MultiAgentQ
from udan.train import (
    EpisodeReplay,
    Run,
    TrainConfig,
    build,
    env_steps,
    episode_returns,
    rollout,
    training_actor,
    training_batch,
    update_round,
)


@dataclass
class Rollout:
    """``n_envs`` whole episodes played by one worker with one set of weights."""

    worker: int
    """Serial number of the worker that played it (a replacement gets a new one)."""
    index: int
    """Its rollout number at that worker (0, 1, ...): (worker, index) names it uniquely."""
    epsilon: float
    episodes: dict[str, np.ndarray]
    """As :meth:`udan.train.EpisodeReplay.compact` has them."""
    returns: np.ndarray
    """Each episode's return per agent (:func:`udan.train.episode_returns`)."""
    steps: int
    seconds: float
    """Time the worker spent playing them: its own throughput, whatever the learner did."""


@dataclass
class WorkerLost:
    """A worker that died (killed, out of memory, its node gone) with a rollout unfinished."""

    worker: int
    reason: str


class RolloutWorker:
    """``n_envs`` environments and an acting copy of the network; seeds from (seed, serial)."""

    def __init__(self, cfg: TrainConfig, spec: ModelSpec, serial: int) -> None:
        torch.set_num_threads(cfg.torch_threads)
        env_seed, act_seed = np.random.SeedSequence(cfg.seed, spawn_key=(serial,)).spawn(2)
        self.env = training_batch(cfg, cfg.n_envs, env_seed)
        self.model = MultiAgentQ(spec)
        self.actor = training_actor(cfg, self.model, self.env)
        self.rng = np.random.default_rng(act_seed)
        self.serial, self.played = serial, 0

    def play(self, weights: dict[str, torch.Tensor], epsilon: float) -> Rollout:
        """One rollout with ``weights`` (the learner's ``state_dict``)."""
        self.model.load_state_dict(weights)
        started = time.perf_counter()
        with_state = self.model.spec.state_dim > 0
        episodes = rollout(self.env, self.actor, epsilon, self.rng, with_state)
        seconds = time.perf_counter() - started
        played = Rollout(
            self.serial,
            self.played,
            epsilon,
            EpisodeReplay.compact(episodes),
            episode_returns(self.env, episodes),
            env_steps(self.env),
            seconds,
        )
        self.played += 1
        return played


class WorkerPool:
    """Rollout requests out to ``slots`` workers, rollouts back in the order they finish.

    A backend starts a worker in a slot (:meth:`_start`), shares weights with the workers
    (:meth:`share`), sends a request (:meth:`submit`) and waits for the next result (:meth:`next`).
    """

    def __init__(self, cfg: TrainConfig, rollout_bytes: int) -> None:
        self.cfg = cfg
        self.spec: ModelSpec | None = None
        self.serials: list[int] = []
        self.started = 0

    @property
    def capacity(self) -> int:
        """Workers this pool can run at once (``--workers``, or what the cluster offers)."""
        raise NotImplementedError

    def start(self, spec: ModelSpec, slots: int, first_serial: int) -> None:
        """``slots`` workers acting with networks of ``spec``, serials from ``first_serial``."""
        self.spec, self.started = spec, first_serial
        self.serials = [-1] * slots
        for slot in range(slots):
            self.replace(slot)

    def replace(self, slot: int) -> int:
        """A new worker, with the next serial, in ``slot``; returns its serial."""
        serial, self.started = self.started, self.started + 1
        self.serials[slot] = serial
        self._start(slot, serial)
        return serial

    def _start(self, slot: int, serial: int) -> None:
        raise NotImplementedError

    def share(self, weights: dict[str, torch.Tensor]) -> Any:
        """A handle on a copy of ``weights`` that requests can carry."""
        raise NotImplementedError

    def submit(self, slot: int, weights: Any, epsilon: float) -> None:
        raise NotImplementedError

    def next(self, timeout: float) -> tuple[int, Rollout | WorkerLost] | None:
        """The next finished request's slot and outcome, or None after ``timeout`` seconds."""
        raise NotImplementedError

    def close(self) -> None:
        """Stop the workers (and what the pool started for them)."""


class LocalPool(WorkerPool):
    """The workers in this process: each request is played when the learner waits for it."""

    def __init__(self, cfg: TrainConfig, rollout_bytes: int) -> None:
        super().__init__(cfg, rollout_bytes)
        self.workers: dict[int, RolloutWorker] = {}
        self.queue: deque[tuple[int, dict, float]] = deque()

    @property
    def capacity(self) -> int:
        return max(self.cfg.workers, 1)

    def _start(self, slot: int, serial: int) -> None:
        self.workers[slot] = RolloutWorker(self.cfg, self.spec, serial)

    def share(self, weights: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {key: value.detach().clone() for key, value in weights.items()}

    def submit(self, slot: int, weights: dict, epsilon: float) -> None:
        self.queue.append((slot, weights, epsilon))

    def next(self, timeout: float) -> tuple[int, Rollout] | None:
        if not self.queue:
            return None
        slot, weights, epsilon = self.queue.popleft()
        return slot, self.workers[slot].play(weights, epsilon)


class RayPool(WorkerPool):
    """Each worker a Ray actor of one CPU; a dead actor is reported as :class:`WorkerLost`.

    Ray starts (or is joined) when the pool is made, with room in its object store for three
    rollouts per worker. Actors are never restarted nor their calls retried by Ray: the learner
    replaces a lost worker itself, with a new serial, so no rollout can arrive twice.
    """

    def __init__(self, cfg: TrainConfig, rollout_bytes: int) -> None:
        super().__init__(cfg, rollout_bytes)
        self.stack = ExitStack()
        store = 3 * max(cfg.workers, 1) * rollout_bytes
        self.cpus = self.stack.enter_context(ray_session(cfg.workers, cfg.address, store))
        self.ray = import_ray()
        self.actors: dict[int, Any] = {}
        self.pending: dict[Any, int] = {}

    @property
    def capacity(self) -> int:
        return self.cfg.workers or max(self.cpus, 1)

    def _start(self, slot: int, serial: int) -> None:
        if slot in self.actors:
            self.ray.kill(self.actors[slot], no_restart=True)
        remote = self.ray.remote(num_cpus=1, max_restarts=0, max_task_retries=0)(RolloutWorker)
        self.actors[slot] = remote.remote(self.cfg, self.spec, serial)

    def share(self, weights: dict[str, torch.Tensor]) -> Any:
        return self.ray.put(weights)

    def submit(self, slot: int, weights: Any, epsilon: float) -> None:
        self.pending[self.actors[slot].play.remote(weights, epsilon)] = slot

    def next(self, timeout: float) -> tuple[int, Rollout | WorkerLost] | None:
        ray = self.ray
        ready, _ = ray.wait(list(self.pending), num_returns=1, timeout=timeout)
        if not ready:
            return None
        slot = self.pending.pop(ready[0])
        try:
            return slot, ray.get(ready[0])
        except (ray.exceptions.RayActorError, ray.exceptions.ObjectLostError) as err:
            return slot, WorkerLost(self.serials[slot], _reason(err))

    def close(self) -> None:
        self.stack.close()


def _reason(err: Exception) -> str:
    """A Ray error's first sentence, for one log line."""
    first = " ".join(str(err).split()).split(". ")[0]
    return first[:120].rstrip(".").lower()


#: Pool backends by name (Ray is imported only when its pool is made).
POOLS: dict[str, type[WorkerPool]] = {"local": LocalPool, "ray": RayPool}


def open_pool(cfg: TrainConfig, rollout_bytes: int) -> WorkerPool:
    """The pool ``cfg.address`` asks for: ``local``, else Ray (started here, or joined);
    ``rollout_bytes``: the size of one rollout, as the replay stores it."""
    return POOLS["local" if cfg.address == "local" else "ray"](cfg, rollout_bytes)


class StopRequest:
    """Ctrl-C (SIGINT) asks the learner to stop after its current update and write a
    checkpoint; a second Ctrl-C interrupts at once. Outside the main thread, where no signal
    arrives, and where SIGINT is ignored (a job started with ``nohup`` or ``&``), it does
    nothing."""

    def __init__(self) -> None:
        self.requested = False
        self.previous: Any = None

    def _handle(self, signum: int, frame: Any) -> None:
        self.requested = True
        signal.signal(signal.SIGINT, self.previous)

    def __enter__(self) -> StopRequest:
        if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
            return self
        try:
            self.previous = signal.signal(signal.SIGINT, self._handle)
        except ValueError:  # not the main thread
            self.previous = None
        return self

    def __exit__(self, *exc: object) -> None:
        if self.previous is not None:
            signal.signal(signal.SIGINT, self.previous)


#: Workers lost one after the other, with no rollout in between, before the run gives up.
LOSSES_IN_A_ROW = 4


def train_with_workers(cfg: TrainConfig, resume: bool = False, log: Callable = print) -> Path:
    """Learn from rollout workers until ``cfg.steps``; returns the checkpoint path.

    The checkpoint is :func:`udan.train.train`'s, plus ``workers`` (:attr:`Learner.ledger`).
    Ctrl-C writes a checkpoint, then raises :class:`KeyboardInterrupt` saying so.
    """
    if cfg.algo == "coma":
        raise EnvConfigError("--workers: coma learns on-policy, in one process")
    if cfg.workers < 0 or cfg.broadcast_every < 1:
        raise EnvConfigError("--workers must be >= 0 and --broadcast-every >= 1")
    torch.set_num_threads(cfg.torch_threads)
    env, model = build(dataclasses.replace(cfg, n_envs=1))  # plays nothing: the task's shapes
    replay = EpisodeReplay.for_run(cfg, env, model.spec)
    episode_bytes = sum(a.nbytes for a in replay.data.values()) // replay.capacity
    pool = open_pool(cfg, cfg.n_envs * episode_bytes)  # first: a bad --address fails fast
    try:
        learner = Learner(Run(cfg, env, resume, ("td_loss", "leader_loss"), log), model, replay)
        pool.start(model.spec, pool.capacity, learner.ledger["started"])
        learner.learn(pool)
    finally:
        pool.close()
    return learner.run.close()


class Learner:
    """The learner's side of the exchange: its networks, replay and run folder, and a ledger
    of the workers: ``started`` (how many; serials go on from there on resume), ``rollouts``
    (counted from each serial), ``lost`` workers and ``refused`` rollouts (already counted),
    and the learner's own seconds ``learning`` (updates) and ``waiting`` (for a rollout): where
    the learner is busy nearly all the time, it, not the workers, sets the pace."""

    def __init__(self, run: Run, model: MultiAgentQ, replay: EpisodeReplay) -> None:
        self.run, self.model, self.replay = run, model, replay
        self.target = copy.deepcopy(model)
        self.optim = torch.optim.Adam(model.parameters(), lr=run.cfg.lr)
        self.ledger = {"started": 0, "rollouts": {}, "lost": 0, "refused": 0}
        self.ledger |= {"learning": 0.0, "waiting": 0.0}
        run.restore(model, self.target, self.optim, replay)
        if run.checkpoint is not None:
            self.ledger |= run.checkpoint.get("workers") or {}
        self.rates: dict[str, float] = {}  # each slot's last rollout throughput, for the log
        self.requested = run.progress["steps"]  # steps of the rollouts counted or asked for
        self.shared: Any = None
        self.shared_at = 0  # updates when the workers' weights were copied

    def learn(self, pool: WorkerPool) -> None:
        """Ask every worker for a rollout, then learn from each as it comes, until the run
        has its steps or Ctrl-C asks to stop (then a checkpoint, and KeyboardInterrupt)."""
        run = self.run
        self.shared, self.shared_at = pool.share(self.model.state_dict()), run.progress["updates"]
        for slot in range(len(pool.serials)):
            self.ask(pool, slot)
        losses_in_a_row = 0
        with StopRequest() as stop:
            while run.running and not stop.requested:
                waited = time.perf_counter()
                got = pool.next(timeout=0.5)
                self.ledger["waiting"] += time.perf_counter() - waited
                if got is None:
                    continue
                slot, result = got
                if isinstance(result, WorkerLost):
                    losses_in_a_row += 1
                    self.replace(pool, slot, result, losses_in_a_row)
                    continue
                losses_in_a_row = 0
                self.ask(pool, slot)  # the worker plays on while the learner learns
                if self.take(slot, result, lambda: stop.requested):
                    self.save(pool)
            if stop.requested:
                self.save(pool)
                steps = run.progress["steps"]
                raise KeyboardInterrupt(f"checkpoint written at {steps:,} steps")

    def ask(self, pool: WorkerPool, slot: int) -> None:
        """The worker in ``slot`` asked for a rollout, unless the run has asked for enough:
        the newest weights copied if ``broadcast_every`` updates passed since the last copy,
        the exploration rate of the steps the rollout will count at."""
        cfg, progress = self.run.cfg, self.run.progress
        if self.requested >= cfg.steps:
            return
        if progress["updates"] - self.shared_at >= cfg.broadcast_every:
            self.shared, self.shared_at = pool.share(self.model.state_dict()), progress["updates"]
        pool.submit(slot, self.shared, self.run.epsilon(self.requested))
        self.requested += cfg.n_envs * self.run.env.config.max_steps

    def replace(self, pool: WorkerPool, slot: int, lost: WorkerLost, in_a_row: int) -> None:
        """A new worker in the lost one's slot, asked for its rollout; the run gives up (with a
        checkpoint) after :data:`LOSSES_IN_A_ROW` losses with no rollout between them."""
        self.requested -= self.run.cfg.n_envs * self.run.env.config.max_steps  # never comes
        self.ledger["lost"] += 1
        if in_a_row >= LOSSES_IN_A_ROW:
            self.save(pool)
            raise ScaleError(
                f"{in_a_row} workers lost in a row (the last: {lost.reason}); "
                f"checkpoint written at {self.run.progress['steps']:,} steps"
            )
        serial = pool.replace(slot)
        self.run.log(f"\nworker {lost.worker} lost ({lost.reason}); worker {serial} takes over")
        self.ask(pool, slot)

    def take(self, slot: int, rollout: Rollout, interrupted: Callable[[], bool]) -> bool:
        """Count a rollout once, learn from it and log it; True when a checkpoint is due."""
        key = str(rollout.worker)
        if rollout.index < self.ledger["rollouts"].get(key, 0):
            self.ledger["refused"] += 1
            return False
        self.ledger["rollouts"][key] = rollout.index + 1
        self.replay.add(rollout.episodes)
        started = time.perf_counter()
        losses = update_round(
            self.model, self.target, self.optim, self.replay, self.run, interrupted
        )
        self.ledger["learning"] += time.perf_counter() - started
        self.rates[f"w{slot}"] = rollout.steps / max(rollout.seconds, 1e-9)
        return self.run.record(rollout.epsilon, losses, rollout.returns, rollout.steps, self.rates)

    def save(self, pool: WorkerPool) -> None:
        self.ledger["started"] = pool.started
        self.run.save(self.model, self.target, self.optim, self.replay, {"workers": self.ledger})
