"""``arena/hidden_goal``: a positive control for communication, stepped B episodes at a time.

A goal cell is hidden somewhere on an empty H x W arena. An agent sees it only when it stands at
it or next to it (Manhattan distance <= 1, the goal's *zone*). Each episode one agent, the
scout, starts inside the zone; the others start anywhere, independently of the goal. Every step
each agent receives the same team reward, the share of agents standing in the zone, so the team
scores fully only when the others get there too. N is drawn per episode (default 2-8).

Nothing but a message can tell an agent where the goal is. An agent's observation holds only
its own position and last action, the walls and the goal within one cell: no other agent is
ever seen, agents never block each other (moves obey walls alone), and no reward is observed.
So an agent's observation history is a function of its own start and actions and the goal
alone; how the others move cannot reach it within the episode, by any path. Without messages
each agent searches alone, and :func:`no_message_bound` caps what any such team can score.

The observation is a spec of its own (:class:`HiddenGoalSpec`, ``name`` and ``version``), not
the find_water/surround one, so models of those tasks are untouched by it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from udan.envs.errors import EnvConfigError, parse_range
from udan.envs.observe import ObsSpec
from udan.envs.rules import ACTION_DELTAS, N_ACTIONS, checked_actions

SPEC_NAME = "hidden_goal"
#: Bumped whenever this task's observation layout or meaning changes.
SPEC_VERSION = 1
#: Planes of the 3x3 window around an agent: off-arena cells, the goal (only in the zone).
CHANNELS: tuple[str, ...] = ("blocked", "goal")
FEATURES: tuple[str, ...] = ("row", "col", *(f"last_action_{i}" for i in range(N_ACTIONS)))
#: The goal's zone: the goal cell and its four neighbours, as (d_row, d_col).
ZONE = np.array([[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]], dtype=np.int64)
_WINDOW = np.array([(r, c) for r in (-1, 0, 1) for c in (-1, 0, 1)], dtype=np.int64)
_IN_ZONE_WINDOW = np.abs(_WINDOW).sum(1) <= 1


@dataclass(frozen=True)
class HiddenGoalSpec(ObsSpec):
    """Shape and meaning of one agent's observation in ``arena/hidden_goal``."""

    view: int = 1
    version: int = SPEC_VERSION
    name: str = SPEC_NAME
    channels: ClassVar[tuple[str, ...]] = CHANNELS
    features: ClassVar[tuple[str, ...]] = FEATURES


@dataclass(frozen=True)
class HiddenGoalConfig:
    """Everything that defines a hidden-goal task; validated on construction."""

    agents: tuple[int, int] = (2, 8)
    """Inclusive range the number of agents is drawn from each episode (one is the scout)."""
    obstacles: tuple[int, int] = (0, 0)
    """Always 0: the arena is empty (accepted so the arena tools can pass it)."""
    height: int = 9
    """Grid rows."""
    width: int = 9
    """Grid columns."""
    max_steps: int = 20
    """Episode length in steps."""
    churn: float = 0.0
    """Always 0: N is fixed within an episode (accepted so the arena tools can pass it)."""
    task: str = field(default=SPEC_NAME, init=False)
    spec: HiddenGoalSpec = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "agents", parse_range(self.agents, "agents"))
        if parse_range(self.obstacles, "obstacles") != (0, 0):
            raise EnvConfigError("hidden_goal: the arena has no obstacles (give 0)")
        if self.churn != 0:
            raise EnvConfigError("hidden_goal: N is fixed within an episode (churn must be 0)")
        if self.agents[0] < 2:
            raise EnvConfigError("hidden_goal: at least 2 agents (a scout and a searcher)")
        if self.height < 2 or self.width < 2:
            raise EnvConfigError(f"arena {self.height}x{self.width} is too small (min 2x2)")
        if self.max_steps < 1:
            raise EnvConfigError("max_steps must be >= 1")
        object.__setattr__(self, "obstacles", (0, 0))
        object.__setattr__(self, "spec", HiddenGoalSpec(self.height, self.width))


def zone_mask(goal: np.ndarray, height: int, width: int) -> np.ndarray:
    """(..., H, W) bool: the cells of each goal's zone (``goal`` (..., 2))."""
    cells = goal[..., None, :] + ZONE  # (..., 5, 2)
    inside = (cells >= 0).all(-1) & (cells < (height, width)).all(-1)
    mask = np.zeros((*goal.shape[:-1], height, width), dtype=bool)
    lead = np.nonzero(inside)
    mask[(*lead[:-1], cells[inside][:, 0], cells[inside][:, 1])] = True
    return mask


class HiddenGoalBatch:
    """B independent hidden-goal episodes stepped together (the arena core's interface)."""

    def __init__(self, config: HiddenGoalConfig, batch: int, seed=0) -> None:
        if batch < 1:
            raise EnvConfigError(f"batch must be >= 1, got {batch}")
        self.config, self.spec, self.batch = config, config.spec, batch
        self.slots = config.agents[1]
        self.rng = np.random.default_rng(seed)
        b, n = batch, self.slots
        self.goal = np.zeros((b, 2), dtype=np.int64)
        self.pos = np.zeros((b, n, 2), dtype=np.int64)
        self.present = np.zeros((b, n), dtype=bool)
        self.scout = np.zeros(b, dtype=np.int64)
        self.agent_id = np.full((b, n), -1, dtype=np.int64)
        self.last_action = np.full((b, n), -1, dtype=np.int64)
        self.episode_return = np.zeros((b, n), dtype=np.float32)
        self.target_score = np.zeros(b, dtype=np.float32)
        self.t = np.zeros(b, dtype=np.int64)
        self.joined = np.zeros((b, n), dtype=bool)
        self.left = np.zeros((b, n), dtype=bool)

    def reset(self, where: np.ndarray | None = None) -> np.ndarray:
        """Start new episodes in the arenas selected by the bool mask ``where`` (default all)."""
        idx = np.arange(self.batch) if where is None else np.flatnonzero(where)
        if idx.size:
            self._reset_arenas(idx)
        return self.observe()

    def _reset_arenas(self, idx: np.ndarray) -> None:
        cfg, rng, k, n = self.config, self.rng, idx.size, self.slots
        h, w = cfg.height, cfg.width
        count = rng.integers(cfg.agents[0], cfg.agents[1] + 1, size=k)
        goal = np.stack([rng.integers(0, h, k), rng.integers(0, w, k)], axis=-1)
        pos = np.stack([rng.integers(0, h, (k, n)), rng.integers(0, w, (k, n))], axis=-1)
        scout = rng.integers(0, count)
        # the scout starts on a uniformly drawn cell of the goal's zone
        zone = goal[:, None, :] + ZONE
        inside = ((zone >= 0) & (zone < (h, w))).all(-1)
        keys = np.where(inside, rng.random(inside.shape), -1.0)
        pos[np.arange(k), scout] = zone[np.arange(k), keys.argmax(1)]
        present = np.arange(n)[None, :] < count[:, None]
        self.goal[idx], self.pos[idx], self.present[idx], self.scout[idx] = (
            goal,
            pos,
            present,
            scout,
        )
        self.agent_id[idx] = np.where(present, np.arange(n)[None, :], -1)
        self.last_action[idx] = -1
        self.episode_return[idx] = 0.0
        self.t[idx] = 0
        self.joined[idx] = present
        self.left[idx] = False

    def in_zone(self) -> np.ndarray:
        """(B, N) bool: present agents at or next to their arena's goal."""
        return (np.abs(self.pos - self.goal[:, None]).sum(-1) <= 1) & self.present

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Apply one action per slot; returns (observations, team rewards (B, N), done (B,))."""
        ended = self.t >= self.config.max_steps
        if ended.any():
            raise ValueError(f"episode over in arena {np.flatnonzero(ended)[0]}: reset it first")
        actions = checked_actions(actions, self.batch, self.slots, self.present)
        moved = self.pos + ACTION_DELTAS[actions]
        inside = ((moved >= 0) & (moved < (self.config.height, self.config.width))).all(-1)
        self.pos = np.where(inside[..., None], moved, self.pos)  # walls alone stop a move
        self.t += 1
        share = self.in_zone().sum(1) / self.present.sum(1)
        reward = np.where(self.present, share[:, None], 0.0).astype(np.float32)
        self.episode_return += reward
        self.last_action = np.where(self.present, actions, -1)
        self.joined[:] = False
        return self.observe(), reward, self.t >= self.config.max_steps

    def observe(self) -> np.ndarray:
        """Every slot's observation (B, N, spec.size); absent slots are zero."""
        cfg = self.config
        cells = self.pos[..., None, :] + _WINDOW  # (B, N, 9, 2)
        blocked = ~((cells >= 0) & (cells < (cfg.height, cfg.width))).all(-1)
        goal = (cells == self.goal[:, None, None, :]).all(-1) & _IN_ZONE_WINDOW
        feats = np.zeros((*self.present.shape, len(FEATURES)), dtype=np.float32)
        feats[..., :2] = self.pos / (max(cfg.height - 1, 1), max(cfg.width - 1, 1))
        feats[..., 2:] = self.last_action[..., None] == np.arange(N_ACTIONS)
        out = np.concatenate([blocked, goal, feats], axis=-1, dtype=np.float32)
        return out * self.present[..., None]

    def global_state(self) -> np.ndarray:
        """Agents and goal as planes (B, 2*H*W), for centralised mixers."""
        cfg, b = self.config, np.arange(self.batch)
        planes = np.zeros((self.batch, 2, cfg.height, cfg.width), dtype=np.float32)
        rows, slots = np.nonzero(self.present)
        planes[rows, 0, self.pos[rows, slots, 0], self.pos[rows, slots, 1]] = 1.0
        planes[b, 1, self.goal[:, 0], self.goal[:, 1]] = 1.0
        return planes.reshape(self.batch, -1)

    def render(self, b: int = 0) -> str:
        """ASCII picture of arena ``b``: G the goal, + its zone, digits agents (s the scout)."""
        cfg = self.config
        chars = np.full((cfg.height, cfg.width), ".")
        chars[zone_mask(self.goal[b], cfg.height, cfg.width)] = "+"
        chars[tuple(self.goal[b])] = "G"
        for slot in np.flatnonzero(self.present[b]):
            chars[tuple(self.pos[b, slot])] = "s" if slot == self.scout[b] else str(slot % 10)
        return "\n".join("".join(row) for row in chars)


def make_batch(name: str, batch: int, seed=0, **options) -> HiddenGoalBatch:
    """Registry factory for ``arena/hidden_goal``."""
    return HiddenGoalBatch(HiddenGoalConfig(**options), batch=batch, seed=seed)


# ------------------------------------------------------------------------------ the two bounds
def zone_size(height: int, width: int) -> np.ndarray:
    """(H, W): how many cells of the arena lie in the zone of a goal at each cell."""
    goal = np.stack(np.indices((height, width)), axis=-1)
    return zone_mask(goal, height, width).sum((-1, -2))


def searcher_bound(height: int, width: int, steps: int) -> np.ndarray:
    """(H, W): an upper bound on a lone searcher's expected score from each start cell.

    A searcher without messages learns nothing until it sees the goal, so up to then its moves
    are a fixed path (a random policy is a mix of fixed paths; none beats the best of them), and
    once it sees the goal it stands in the zone, where it scores 1 a step. With the goal uniform
    over the F = H*W cells and independent of the start s, P(seen by step t) = |C_t|/F, where
    C_t is the set of cells within 1 of the path up to step t. So the score is at most
    sum_{t=1..T} max |C_t| / F, and |C_t| is at most the cells of the arena within t+1 of s
    (the path stays within t of s), and at most |C_0| + 3t (a move brings at most 3 new cells
    into view; a wait none).
    """
    cells = np.stack(np.indices((height, width)), axis=-1).reshape(-1, 2)
    dist = np.abs(cells[:, None, :] - cells[None, :, :]).sum(-1)  # (F, F) start x cell
    seen0 = (dist <= 1).sum(1)
    t = np.arange(1, steps + 1)
    ball = (dist[:, None, :] <= (t + 1)[None, :, None]).sum(-1)  # (F, T)
    cover = np.minimum(ball, seen0[:, None] + 3 * t[None, :])
    return (cover.sum(1) / (height * width)).reshape(height, width)


def no_message_bound(height: int, width: int, steps: int, agents: int) -> float:
    """Upper bound on the team score (mean agent return) of agents without messages.

    Every agent receives the share of agents in the zone, so the team score is the mean over
    agents of the steps each spends in the zone, and no agent can change another's. The scout
    (one of N) starts in the zone and can stay: T. A searcher starts uniformly, independently of
    the goal, and alone scores at most :func:`searcher_bound` on average.
    """
    searcher = float(searcher_bound(height, width, steps).mean())
    return (steps + (agents - 1) * searcher) / agents


def oracle_score(height: int, width: int, steps: int, agents: int) -> float:
    """The full-information team score, exactly: every searcher walks straight into the zone.

    Nothing blocks a walk, so a searcher d = max(|dr| + |dc| - 1, 0) moves from the zone is in
    it after move d and scores at every step from then on: T + 1 - d steps (T when d = 0, 0
    when d > T); averaged over uniform start and goal cells.
    """
    cells = np.stack(np.indices((height, width)), axis=-1).reshape(-1, 2)
    reach = np.maximum(np.abs(cells[:, None, :] - cells[None, :, :]).sum(-1) - 1, 0)
    searcher = float(np.clip(steps + 1 - reach, 0, steps).mean())
    return (steps + (agents - 1) * searcher) / agents
