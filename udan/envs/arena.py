"""The arena of the physical experiments (paper §V-B), stepped B episodes at a time in numpy.

Two tasks on a 9x9 grid, five actions (:mod:`udan.envs.rules`), 50 steps, view radius 3:

- ``find_water``: rows 0-1 are the water zone (a row of as many sources as agents at row 0,
  walled at both ends, the arena edge behind; agents drink from the cell in front of a source,
  row 1), rows 2-4 the obstacle zone, rows 5-8 the start zone. An agent on a drinking cell gets 1
  per step, so the best average is 50 minus the travel time.
- ``surround``: agents, obstacles and a target anywhere. The target moves at speed 1 at the same
  time as the agents, under the same conflict rules, fleeing what it sees within
  ``target_view`` (1), so an agent that follows it into the cell it leaves stays next to it.
  An agent next to it (4-neighbour) scores 1 per step; one that is not loses 1 every fourth
  step. The target's own score drops by 1 for every step some agent is next to it;
  ``adjacent_steps`` counts, per agent, the steps it ended next to it (the paper's Table V
  "goal score" is minus their mean over agents: docs/environments.md).

The number of agents and obstacles is drawn per episode; with ``churn`` > 0 an agent may also
join or leave during an episode (within ``agents``, so churn needs a range). The world is
physical: an agent that joins find_water mid-episode finds the water sources the episode started
with (one per agent at the start), not a new one of its own. Arenas are padded to ``agents[1]``
slots; ``present`` says which slots hold an agent and ``agent_id`` gives each a stable id within
its episode.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from udan import _kernels
from udan.envs.errors import EnvConfigError, parse_range
from udan.envs.observe import (
    AGENT_BIT,
    BLOCKED_BIT,
    CHANNELS,
    OBJECTIVE_BIT,
    ObsSpec,
    observe,
    pad_layout,
)
from udan.envs.rules import (
    ACTION_DELTAS,
    FREE,
    N_ACTIONS,
    OBSTACLE,
    WALL,
    WATER,
    checked_actions,
    resolve_moves,
)

TASKS = ("find_water", "surround")
# Cell code -> observation bits of the static layout.
_LAYOUT_BITS = np.zeros(4, dtype=np.uint8)
_LAYOUT_BITS[[WALL, OBSTACLE]] = BLOCKED_BIT
_LAYOUT_BITS[WATER] = BLOCKED_BIT | OBJECTIVE_BIT


@dataclass(frozen=True)
class ArenaConfig:
    """Everything that defines an arena task; validated on construction."""

    task: str = "find_water"
    """``find_water`` or ``surround``."""
    agents: tuple[int, int] = (1, 5)
    """Inclusive range the number of agents is drawn from each episode."""
    obstacles: tuple[int, int] = (0, 14)
    """Inclusive range the number of obstacle cells is drawn from each episode."""
    height: int = 9
    """Grid rows."""
    width: int = 9
    """Grid columns."""
    max_steps: int = 50
    """Episode length in steps."""
    view: int = 3
    """Observation radius of an agent (window is 2*view+1 square)."""
    target_view: int = 1
    """How far the surround target sees agents to flee them."""
    churn: float = 0.0
    """Per-step probability that one agent joins or leaves mid-episode (0 = fixed N)."""
    spec: ObsSpec = field(init=False)

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise EnvConfigError(f"unknown arena task {self.task!r}; known: {', '.join(TASKS)}")
        object.__setattr__(self, "agents", parse_range(self.agents, "agents"))
        object.__setattr__(self, "obstacles", parse_range(self.obstacles, "obstacles"))
        if self.height < 2 or self.width < 2:
            raise EnvConfigError(f"arena {self.height}x{self.width} is too small (min 2x2)")
        if self.agents[0] < 1:
            raise EnvConfigError("agents: at least 1 agent is needed")
        if self.max_steps < 1 or self.view < 0 or self.target_view < 0:
            raise EnvConfigError("max_steps must be >= 1 and view radii >= 0")
        if not 0.0 <= self.churn <= 1.0:
            raise EnvConfigError(f"churn {self.churn} is not a probability")
        if self.churn > 0 and self.agents[0] == self.agents[1]:
            raise EnvConfigError(
                f"churn needs a range of agents to move in; agents is fixed at {self.agents[0]}"
            )
        agents_hi, obstacles_hi = self.agents[1], self.obstacles[1]
        if self.task == "find_water":
            if self.height < 4:
                raise EnvConfigError(
                    "find_water needs at least 4 rows (water, front, obstacles, start)"
                )
            if agents_hi > self.width:
                raise EnvConfigError(
                    f"find_water: {agents_hi} agents need {agents_hi} water sources, "
                    f"but a row has only {self.width} cells"
                )
            if agents_hi > len(self.start_cells):
                raise EnvConfigError(
                    f"find_water: {agents_hi} agents do not fit the "
                    f"{len(self.start_cells)}-cell start zone"
                )
            if obstacles_hi > len(self.obstacle_cells):
                raise EnvConfigError(
                    f"find_water: {obstacles_hi} obstacles do not fit the "
                    f"{len(self.obstacle_cells)}-cell obstacle zone"
                )
        elif agents_hi + obstacles_hi + 1 > self.height * self.width:
            raise EnvConfigError(
                f"surround: {agents_hi} agents + {obstacles_hi} obstacles + 1 target "
                f"exceed the {self.height * self.width} cells"
            )
        object.__setattr__(self, "spec", ObsSpec(self.height, self.width, self.view))

    @property
    def obstacle_rows(self) -> range:
        """find_water: the rows between the water front (row 1) and the start zone."""
        return range(2, 2 + (self.height - 2) // 2)

    @property
    def obstacle_cells(self) -> np.ndarray:
        """Flat indices of the find_water obstacle zone."""
        rows = self.obstacle_rows
        return np.arange(rows.start * self.width, rows.stop * self.width)

    @property
    def start_cells(self) -> np.ndarray:
        """Flat indices where agents appear (find_water: the start zone; surround: anywhere)."""
        if self.task == "surround":
            return np.arange(self.height * self.width)
        return np.arange(self.obstacle_rows.stop * self.width, self.height * self.width)


def _pick(
    rng: np.random.Generator,
    candidates: np.ndarray,
    counts: np.ndarray,
    slots: int,
    taken: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per row b, ``counts[b]`` distinct random cells from ``candidates`` not in ``taken[b]``.

    Returns (cells (B, slots), valid (B, slots)); one argsort over random keys, no Python loop.
    """
    keys = rng.random((counts.shape[0], candidates.size))
    if taken is not None:
        keys[taken[:, candidates]] = np.inf
    order = np.argsort(keys, axis=1)[:, :slots]
    return candidates[order], np.arange(slots)[None, :] < counts[:, None]


def layout_bits(layout: np.ndarray, view: int) -> np.ndarray:
    """Observation bits (B, H+2v, W+2v) of static layouts (B, H, W) of rules cell codes."""
    return pad_layout(_LAYOUT_BITS[layout], view)


_NO_TARGET = np.zeros((0, 2), np.int64)  # find_water has none


def scene_codes(
    padded_layout: np.ndarray,
    pos: np.ndarray,
    present: np.ndarray,
    view: int,
    target: np.ndarray | None = None,
) -> np.ndarray:
    """What :func:`udan.envs.observe.observe` reads: the padded layout bits (B, H+2v, W+2v)
    with every present agent's cell and the surround ``target`` (B, 2) cell marked (present
    agents stand on the arena). The arena core and the edge (which builds the scene from
    camera markers) both call this; one copy and one loop in C (``udan._kernels``)."""
    present = np.ascontiguousarray(present, bool)
    codes = np.empty(np.shape(padded_layout), np.uint8)
    _kernels.scene_codes(
        np.ascontiguousarray(padded_layout, np.uint8),
        np.ascontiguousarray(pos, np.int64),
        present,
        _NO_TARGET if target is None else np.ascontiguousarray(target, np.int64),
        view,
        AGENT_BIT,
        OBJECTIVE_BIT,
        codes,
    )
    return codes


def task_rewards(
    task: str,
    layout: np.ndarray,
    pos: np.ndarray,
    present: np.ndarray,
    target: np.ndarray | None,
    t: np.ndarray,
) -> np.ndarray:
    """Per-agent rewards (B, N) of one step that has just ended (``t`` (B,) counts it).

    find_water: 1 on a cell in front of a source. surround: 1 next to the target, else -1 every
    fourth step. Absent agents get 0. Shared by the arena core, the edge and the HIL world; one
    loop in C (``udan._kernels.task_rewards``).
    """
    present = np.ascontiguousarray(present, bool)
    out = np.empty(present.shape, np.float32)
    find_water = task == "find_water"
    _kernels.task_rewards(
        find_water,
        np.ascontiguousarray(layout, np.uint8),
        np.ascontiguousarray(pos, np.int64),
        present,
        _NO_TARGET if find_water else np.ascontiguousarray(target, np.int64),
        np.ascontiguousarray(t, np.int64),
        WATER,
        out,
    )
    return out


class ArenaBatch:
    """B independent arena episodes stepped together; all arrays have the batch on axis 0."""

    def __init__(self, config: ArenaConfig, batch: int, seed: int | None = 0) -> None:
        if batch < 1:
            raise EnvConfigError(f"batch must be >= 1, got {batch}")
        self.config = config
        self.spec = config.spec
        self.batch = batch
        self.slots = config.agents[1]
        self.rng = np.random.default_rng(seed)
        h, w, b, n = config.height, config.width, batch, self.slots
        self.layout = np.zeros((b, h, w), dtype=np.uint8)
        self.pos = np.zeros((b, n, 2), dtype=np.int64)
        self.present = np.zeros((b, n), dtype=bool)
        self.agent_id = np.full((b, n), -1, dtype=np.int64)
        self.next_id = np.zeros(b, dtype=np.int64)
        self.last_action = np.full((b, n), -1, dtype=np.int64)
        self.last_reward = np.zeros((b, n), dtype=np.float32)
        self.episode_return = np.zeros((b, n), dtype=np.float32)
        self.target = np.zeros((b, 2), dtype=np.int64)
        self.target_score = np.zeros(b, dtype=np.float32)
        self.adjacent_steps = np.zeros((b, n), dtype=np.int64)
        self.t = np.zeros(b, dtype=np.int64)
        self.joined = np.zeros((b, n), dtype=bool)
        self.left = np.zeros((b, n), dtype=bool)
        self._padded_layout = np.zeros((b, h + 2 * config.view, w + 2 * config.view), np.uint8)

    # ------------------------------------------------------------------ episodes
    def reset(self, where: np.ndarray | None = None) -> np.ndarray:
        """Start new episodes in the arenas selected by the bool mask ``where`` (default all)."""
        idx = np.arange(self.batch) if where is None else np.flatnonzero(where)
        if idx.size:
            self._reset_arenas(idx)
        return self.observe()

    def _reset_arenas(self, idx: np.ndarray) -> None:
        cfg, rng, k = self.config, self.rng, idx.size
        h, w = cfg.height, cfg.width
        n_agents = rng.integers(cfg.agents[0], cfg.agents[1] + 1, size=k)
        n_obst = rng.integers(cfg.obstacles[0], cfg.obstacles[1] + 1, size=k)
        layout = np.zeros((k, h * w), dtype=np.uint8)
        rows = np.arange(k)[:, None]
        if cfg.task == "find_water":
            first = (w - n_agents) // 2
            cols = np.arange(w)[None, :]
            row0 = np.where(
                (cols >= first[:, None]) & (cols < (first + n_agents)[:, None]), WATER, FREE
            )
            row0[(cols == first[:, None] - 1) | (cols == (first + n_agents)[:, None])] = WALL
            layout[:, :w] = row0
            cells, valid = _pick(rng, cfg.obstacle_cells, n_obst, cfg.obstacles[1])
            layout[np.broadcast_to(rows, cells.shape)[valid], cells[valid]] = OBSTACLE
            agent_cells, agent_valid = _pick(rng, cfg.start_cells, n_agents, self.slots)
        else:
            total = cfg.obstacles[1] + self.slots + 1
            cells, _ = _pick(rng, cfg.start_cells, np.full(k, total), total)
            obst_valid = np.arange(cfg.obstacles[1])[None, :] < n_obst[:, None]
            obst = cells[:, : cfg.obstacles[1]]
            layout[np.broadcast_to(rows, obst.shape)[obst_valid], obst[obst_valid]] = OBSTACLE
            # agents and target take the cells right after this arena's obstacles
            after = n_obst[:, None] + np.arange(self.slots + 1)[None, :]
            chosen = np.take_along_axis(cells, after, axis=1)
            agent_cells, target_cell = chosen[:, :-1], chosen[:, -1]
            agent_valid = np.arange(self.slots)[None, :] < n_agents[:, None]
            self.target[idx] = np.stack([target_cell // w, target_cell % w], axis=-1)
        self.layout[idx] = layout.reshape(k, h, w)
        self._padded_layout[idx] = layout_bits(self.layout[idx], cfg.view)
        self.pos[idx] = np.stack([agent_cells // w, agent_cells % w], axis=-1)
        self.present[idx] = agent_valid
        self.agent_id[idx] = np.where(agent_valid, np.arange(self.slots)[None, :], -1)
        self.next_id[idx] = n_agents
        self.last_action[idx] = -1
        self.last_reward[idx] = 0.0
        self.episode_return[idx] = 0.0
        self.target_score[idx] = 0.0
        self.adjacent_steps[idx] = 0
        self.t[idx] = 0
        self.joined[idx] = agent_valid
        self.left[idx] = False

    # ------------------------------------------------------------------ stepping
    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Apply one integer action per slot (ignored for absent slots); a step past an
        episode's end is an error.

        Returns (observations (B, N, D), rewards (B, N), done (B,)). Episodes are not reset
        automatically; call :meth:`reset` with ``done``.
        """
        ended = self.t >= self.config.max_steps
        if ended.any():
            raise ValueError(f"episode over in arena {np.flatnonzero(ended)[0]}: reset it first")
        actions = checked_actions(actions, self.batch, self.slots, self.present)
        passable = self.layout == FREE
        if self.config.task == "surround":
            # the target is one more mover under the same rules, deciding from positions at t
            both = resolve_moves(
                np.concatenate([self.pos, self.target[:, None]], axis=1),
                np.concatenate([actions, self._target_action()[:, None]], axis=1),
                passable,
                np.concatenate([self.present, np.ones((self.batch, 1), bool)], axis=1),
            )
            self.pos, self.target = both[:, :-1], both[:, -1]
        else:
            self.pos = resolve_moves(self.pos, actions, passable, self.present)
        self.t += 1
        reward = self._rewards()
        self.episode_return += reward
        self.last_action = np.where(self.present, actions, -1)
        self.last_reward = reward
        self.joined[:] = False
        self.left[:] = False
        if self.config.churn > 0:
            self._churn()
        return self.observe(), reward, self.t >= self.config.max_steps

    def _rewards(self) -> np.ndarray:
        reward = task_rewards(
            self.config.task, self.layout, self.pos, self.present, self.target, self.t
        )
        if self.config.task == "surround":
            adjacent = (np.abs(self.pos - self.target[:, None]).sum(-1) == 1) & self.present
            self.target_score -= adjacent.any(axis=1)
            self.adjacent_steps += adjacent
        return reward

    def flee_scores(self) -> np.ndarray:
        """How good each target action is (B, 5): -inf where blocked, else the distance it keeps
        from the nearest agent it sees (0 for every free move when it sees none)."""
        cfg, batch = self.config, np.arange(self.batch)[:, None]
        rows = self.target[:, 0:1] + ACTION_DELTAS[:, 0]  # (B, 5)
        cols = self.target[:, 1:2] + ACTION_DELTAS[:, 1]
        inside = (rows >= 0) & (rows < cfg.height) & (cols >= 0) & (cols < cfg.width)
        rows_c = np.clip(rows, 0, cfg.height - 1)
        cols_c = np.clip(cols, 0, cfg.width - 1)
        free = inside & (self.layout[batch, rows_c, cols_c] == FREE)
        free &= ~self.occupancy()[batch, rows_c, cols_c]
        agent_r, agent_c = self.pos[..., 0], self.pos[..., 1]
        seen = (
            self.present
            & (np.abs(agent_r - self.target[:, 0:1]) <= cfg.target_view)
            & (np.abs(agent_c - self.target[:, 1:2]) <= cfg.target_view)
        )
        nearest = np.full(rows.shape, np.iinfo(np.int64).max)
        for slot in range(self.slots):  # a handful of slots: cheaper than a tiny-axis reduce
            dist = np.abs(rows - agent_r[:, slot : slot + 1]) + np.abs(
                cols - agent_c[:, slot : slot + 1]
            )
            np.minimum(nearest, np.where(seen[:, slot : slot + 1], dist, nearest), out=nearest)
        score = np.where(seen.any(1)[:, None], nearest, 0).astype(np.float64)
        score[~free] = -np.inf
        return score

    def occupancy(self) -> np.ndarray:
        """(B, H, W) bool: cells holding a present agent."""
        cfg = self.config
        occ = np.zeros((self.batch, cfg.height, cfg.width), dtype=bool)
        b, s = np.nonzero(self.present)
        occ[b, self.pos[b, s, 0], self.pos[b, s, 1]] = True
        return occ

    def _target_action(self) -> np.ndarray:
        """The target flees the agents it sees; ties (and no agent in view) are broken at random."""
        score = self.flee_scores() + self.rng.random((self.batch, N_ACTIONS)) * 0.5
        return score.argmax(-1)

    def _churn(self) -> None:
        """With probability ``churn`` per arena, one agent leaves or a new one joins."""
        cfg, rng = self.config, self.rng
        for b in np.flatnonzero(rng.random(self.batch) < cfg.churn):
            count = int(self.present[b].sum())
            join = rng.random() < 0.5
            if join and count < self.slots:
                occupied = (self.occupancy()[b] | (self.layout[b] != FREE)).ravel()
                if cfg.task == "surround":
                    occupied[self.target[b, 0] * cfg.width + self.target[b, 1]] = True
                free = cfg.start_cells[~occupied[cfg.start_cells]]
                if free.size == 0:
                    continue
                cell = rng.choice(free)
                slot = np.flatnonzero(~self.present[b])[0]
                self.pos[b, slot] = (cell // cfg.width, cell % cfg.width)
                self.present[b, slot] = True
                self.agent_id[b, slot] = self.next_id[b]
                self.next_id[b] += 1
                self.last_action[b, slot] = -1
                self.last_reward[b, slot] = 0.0
                self.episode_return[b, slot] = 0.0
                self.adjacent_steps[b, slot] = 0
                self.joined[b, slot] = True
            elif not join and count > max(cfg.agents[0], 1):
                slot = rng.choice(np.flatnonzero(self.present[b]))
                self.present[b, slot] = False
                self.left[b, slot] = True

    # ------------------------------------------------------------------ views
    def cell_codes(self) -> np.ndarray:
        """Padded observation bit codes (B, H+2v, W+2v): layout, agents and the target."""
        target = self.target if self.config.task == "surround" else None
        return scene_codes(self._padded_layout, self.pos, self.present, self.config.view, target)

    def observe(self) -> np.ndarray:
        """Every slot's observation (B, N, spec.size); absent slots are zero."""
        return observe(
            self.spec, self.cell_codes(), self.pos, self.last_action, self.last_reward, self.present
        )

    def global_state(self) -> np.ndarray:
        """The whole arena as planes (B, 3*H*W) for centralised critics/mixers (QMIX, COMA)."""
        v = self.config.view
        codes = self.cell_codes()[:, v : v + self.config.height, v : v + self.config.width]
        bits = np.array([BLOCKED_BIT, AGENT_BIT, OBJECTIVE_BIT], dtype=np.uint8)
        planes = (codes[:, None] & bits[None, :, None, None]) != 0
        return planes.reshape(
            self.batch, len(CHANNELS) * self.config.height * self.config.width
        ).astype(np.float32)

    def render(self, b: int = 0) -> str:
        """ASCII picture of arena ``b``: # wall, o obstacle, ~ water, T target, digits agents."""
        chars = np.array([".", "#", "o", "~"])[self.layout[b]]
        if self.config.task == "surround":
            chars[tuple(self.target[b])] = "T"
        for slot in np.flatnonzero(self.present[b]):
            chars[tuple(self.pos[b, slot])] = str(self.agent_id[b, slot] % 10)
        return "\n".join("".join(row) for row in chars)


def make_batch(name: str, batch: int, seed: int | None = 0, **options) -> ArenaBatch:
    """Registry factory: ``arena/<task>`` -> :class:`ArenaBatch` of ``batch`` arenas."""
    task = name.removeprefix("arena/")
    return ArenaBatch(ArenaConfig(task=task, **options), batch=batch, seed=seed)
