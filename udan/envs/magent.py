"""MAgent scenarios of the paper (§V-A) on the real MAgent2 engine, as PettingZoo ParallelEnvs.

``make("magent/pursuit" | "magent/tiger" | "magent/queue", agents=(8, 20), ...)`` gives an env
whose number of learning agents is drawn anew at every reset, which is what UDAN trains on.
MAgent2 (``magent2.gridworld.GridWorld`` and its C library) moves the agents, resolves attacks,
keeps hit points and evaluates the reward rules; this module only draws the episode's counts,
places agents and walls, drives the scripted opponents and packs observations.

What MAgent2 cannot express, and what is done about it:

* counts per episode: a GridWorld's groups have no size; one engine is built per env and every
  reset clears it and adds this episode's walls and agents at positions drawn here (``custom``
  placement), so counts, layouts and the opponents are reproducible from the env seed;
* scripted opponents: the engine takes actions only; sheep and deer policies run in Python;
* step limit: the engine has none; ``max_steps`` truncates here. Everything else that ends an
  episode is the engine's own game over (a terminal reward rule fired, or a group is wiped out).

All rewards are MAgent2 reward rules, the queue's formation reward included: MAgent2's
``in_a_line`` event over a whole group (``index="all"``) pays a group reward. The engine adds a
group reward to every member and resets it only in ``clear_dead``, which :meth:`MagentEnv.step`
calls after every engine step, as MAgent2's own PettingZoo envs do.

Observation of a learning agent (one float32 vector; MAgent2's own view and features, flattened)::

    [ view (2r+1, 2r+1, C) flattened row-major: rows = dy, cols = dx, channel last
    | embedding (10 bits of the engine's agent id)
    | last action one-hot (A)
    | last reward (1)
    | own position x / (map_size - 1), y / (map_size - 1) (2) ]

View channels ``C`` are wall/off-map, own-team presence, own-team hp / max hp, and, where there
is an opponent group, opponent presence and opponent hp / max hp. Cells outside the view circle
are 0. MAgent2 can give the position only together with a global density "minimap" in every view,
which would break partial observability, so the position is read with ``get_pos`` instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from inspect import signature
from typing import Any, ClassVar

import magent2
import numpy as np
from gymnasium import spaces
from magent2 import gridworld as gw
from pettingzoo import ParallelEnv

from udan.envs.errors import EnvConfigError, parse_range
from udan.envs.magent_spec import EMBEDDING_SIZE, MagentSpec

#: ``state()`` pools the whole-map planes down to at most this many cells per side.
STATE_GRID = 20
#: Smallest map accepted: MAgent2 walls the outermost ring, leaving a 3x3 interior.
MIN_MAP_SIZE = 5


def move_offsets(speed: float) -> np.ndarray:
    """``(dx, dy)`` of each MAgent2 move action for an agent of ``speed``, in action order.

    The engine's move actions are the cells of a circle of radius ``speed`` (the stay cell
    included) in row-major order; the scripted opponents need the table to pick a move.
    """
    r = math.floor(speed)
    cells = [
        (dx, dy)
        for dy in range(-r, r + 1)
        for dx in range(-r, r + 1)
        if dx * dx + dy * dy <= speed * speed
    ]
    return np.array(cells, dtype=np.int64)


class MagentEnv(ParallelEnv):
    """One MAgent2 scenario with a learning group (``agent_i``) and an optional scripted group.

    Subclasses give the engine attributes, the reward rules and the opponents' policy. Build
    through :func:`make`.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["ansi"], "is_parallelizable": True}

    #: Per-scenario defaults (paper §V-A).
    default_map_size: ClassVar[int]
    default_max_steps: ClassVar[int]
    #: Opponents placed per learning agent (0: no opponent group).
    default_prey_per_agent: ClassVar[float] = 0.0
    #: Engine attributes of the learning agents and of the opponents.
    agent_attrs: ClassVar[dict[str, Any]]
    opponent_attrs: ClassVar[dict[str, Any] | None] = None

    def __init__(
        self,
        name: str,
        agents: int | str | tuple[int, int] = (8, 20),
        obstacles: int | str | tuple[int, int] = 0,
        seed: int | None = None,
        max_steps: int | None = None,
        map_size: int | None = None,
        prey_per_agent: float | None = None,
        render_mode: str | None = None,
    ) -> None:
        self.metadata = {**type(self).metadata, "name": name}
        self.agent_range = parse_range(agents, "agents")
        self.obstacle_range = parse_range(obstacles, "obstacles")
        self.map_size = self.default_map_size if map_size is None else map_size
        self.max_steps = self.default_max_steps if max_steps is None else max_steps
        if prey_per_agent is None:
            prey_per_agent = self.default_prey_per_agent
        elif self.opponent_attrs is None:
            raise EnvConfigError(f"{name}: has no opponents, prey_per_agent does not apply")
        self.prey_per_agent = float(prey_per_agent)
        if render_mode not in (None, "ansi"):
            raise EnvConfigError(f"{name}: render_mode must be None or 'ansi', got {render_mode!r}")
        self.render_mode = render_mode
        self._validate(name)

        self._engine = magent2.GridWorld(self._config())
        handles = self._engine.get_handles()
        self._handle = handles[0]
        self._opp_handle = handles[1] if len(handles) > 1 else None

        self.possible_agents = [f"agent_{i}" for i in range(self.agent_range[1])]
        self.agents: list[str] = []
        view = tuple(int(v) for v in self._engine.get_view_space(self._handle))
        n_feat = int(self._engine.get_feature_space(self._handle)[0])
        n_actions = int(self._engine.get_action_space(self._handle)[0])
        self.view_shape = view
        self.obs_size = int(np.prod(view)) + n_feat + 2
        low = np.zeros(self.obs_size, dtype=np.float32)
        high = np.ones(self.obs_size, dtype=np.float32)
        low[-3], high[-3] = -np.inf, np.inf  # last reward
        self._obs_space = spaces.Box(low, high, dtype=np.float32)
        self._act_space = spaces.Discrete(n_actions)
        self.observation_spaces = dict.fromkeys(self.possible_agents, self._obs_space)
        self.action_spaces = dict.fromkeys(self.possible_agents, self._act_space)
        self.stay_action = int(
            np.flatnonzero((move_offsets(self.agent_attrs["speed"]) == 0).all(1))[0]
        )

        self._block = math.ceil(self.map_size / STATE_GRID)
        self._state_grid = math.ceil(self.map_size / self._block)
        n_planes = 1 + 2 * len(handles)
        self.state_space = spaces.Box(
            0.0, 1.0, (self._state_grid**2 * n_planes + 1,), dtype=np.float32
        )

        self._rng = np.random.default_rng(seed)
        self._walls = np.zeros((self.map_size, self.map_size), dtype=bool)
        self._id_to_name: dict[int, str] = {}
        self._steps = 0

    # ----- configuration -------------------------------------------------------------------

    def _validate(self, name: str) -> None:
        if not isinstance(self.map_size, int) or self.map_size < MIN_MAP_SIZE:
            raise EnvConfigError(f"{name}: map_size must be an int >= {MIN_MAP_SIZE}")
        if not isinstance(self.max_steps, int) or self.max_steps < 1:
            raise EnvConfigError(f"{name}: max_steps must be an int >= 1")
        if self.agent_range[0] < 1:
            raise EnvConfigError(f"{name}: agents must be at least 1, got {self.agent_range}")
        if self.opponent_attrs is not None and not self.prey_per_agent > 0:
            raise EnvConfigError(f"{name}: prey_per_agent must be > 0")
        hi = self.agent_range[1]
        need = hi + self._n_opponents(hi) + self.obstacle_range[1]
        room = (self.map_size - 2) ** 2
        if need > room:
            raise EnvConfigError(
                f"{name}: up to {need} cells of agents, opponents and obstacles do not fit in the "
                f"{room} free cells of a {self.map_size}x{self.map_size} map"
            )

    def _n_opponents(self, n_agents: int) -> int:
        if self.opponent_attrs is None:
            return 0
        return max(1, round(self.prey_per_agent * n_agents))

    def _config(self) -> gw.Config:
        cfg = gw.Config()
        cfg.set({"map_width": self.map_size, "map_height": self.map_size})
        cfg.set({"embedding_size": EMBEDDING_SIZE})
        group = cfg.add_group(cfg.register_agent_type("agent", self._attrs(self.agent_attrs)))
        opp = None
        if self.opponent_attrs is not None:
            opp = cfg.add_group(
                cfg.register_agent_type("opponent", self._attrs(self.opponent_attrs))
            )
        self._reward_rules(cfg, group, opp)
        return cfg

    @staticmethod
    def _attrs(attrs: dict[str, Any]) -> dict[str, Any]:
        """Engine attributes: ``view``/``attack`` radii become MAgent2 circle ranges."""
        out = {k: v for k, v in attrs.items() if k not in ("view", "attack")}
        out.update(
            width=1,
            length=1,
            view_range=gw.CircleRange(attrs["view"]),
            attack_range=gw.CircleRange(attrs["attack"]),
        )
        return out

    def _reward_rules(self, cfg: gw.Config, group: int, opp: int | None) -> None:
        """Add the scenario's MAgent2 reward rules (none by default)."""

    # ----- PettingZoo API ------------------------------------------------------------------

    def observation_space(self, agent: str) -> spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Discrete:
        return self.action_spaces[agent]

    def attack_action(self, dx: int, dy: int) -> int:
        """The action with which a learning agent attacks the cell ``(dx, dy)`` away from it.

        Scripted baselines and tests need it; MAgent2 numbers attacks after the moves.
        """
        base, table = self._engine.get_view2attack(self._handle)
        c = table.shape[0] // 2
        k = table[c + dy, c + dx] if max(abs(dx), abs(dy)) <= c else -1
        if k < 0:
            raise ValueError(f"cell ({dx}, {dy}) is out of attack range")
        return int(base + k)

    def positions(self) -> tuple[np.ndarray, np.ndarray]:
        """``(x, y)`` cells of the learning agents (engine order) and of the opponents."""
        opp = self._opp_handle
        none = np.zeros((0, 2), dtype=np.int32)
        return (
            self._engine.get_pos(self._handle),
            self._engine.get_pos(opp) if opp is not None and self._engine.get_num(opp) else none,
        )

    @property
    def walls(self) -> np.ndarray:
        """``walls[x, y]``: the cell is a wall (the border included) in this episode."""
        return self._walls

    def potential(self) -> dict[str, float]:
        """Each engine-held learning agent's nearness to the closest opponent, as far as it sees:
        ``-min(d, view) / view`` with ``d`` the Euclidean distance in cells, so -1 with no
        opponent in view (or none left) and 0 on top of one. Training's reward shaping
        (``udan-train --shaping``) reads it; the task's own rewards never do. Queue, with no
        opponents, has its own."""
        cells, opponents = self.agent_cells(), self.positions()[1]
        view = float(self.agent_attrs["view"])
        near = np.full(len(cells), view)
        if len(cells) and len(opponents):
            own = np.array(list(cells.values()), dtype=np.float64)
            gaps = own[:, None, :] - opponents[None, :, :]
            near = np.minimum(np.hypot(gaps[..., 0], gaps[..., 1]).min(axis=1), view)
        return dict(zip(cells, (-near / view).tolist(), strict=True))

    def agent_cells(self) -> dict[str, np.ndarray]:
        """``(x, y)`` cell of every learning agent the engine still holds, by agent name."""
        ids = self._engine.get_agent_id(self._handle)
        cells = self._engine.get_pos(self._handle)
        return {self._id_to_name[int(i)]: cell for i, cell in zip(ids, cells, strict=True)}

    def spec(self) -> MagentSpec:
        """The observation spec of this scenario's learning agents."""
        n_moves = len(move_offsets(self.agent_attrs["speed"]))
        return MagentSpec(
            self.map_size,
            self.map_size,
            self.view_shape[0] // 2,
            scenario=self.metadata["name"],
            opponents=self._opp_handle is not None,
            n_moves=n_moves,
            n_attacks=int(self._act_space.n) - n_moves,
        )

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        """New episode: draw counts, walls and positions; ``options["layout"]`` fixes them.

        A layout is ``{"agents": [(x, y), ...], "opponents": [...], "walls": [...]}`` (cells
        inside the border); it lets tests and evaluations stage exact situations.
        """
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        layout = (options or {}).get("layout")
        eng = self._engine
        eng.reset()
        eng.set_seed(int(self._rng.integers(2**31 - 1)))
        agents, opponents, walls = (
            self._draw_layout() if layout is None else self._check_layout(layout)
        )
        self._walls[:] = False
        self._walls[[0, -1], :] = self._walls[:, [0, -1]] = True
        if len(walls):
            self._walls[walls[:, 0], walls[:, 1]] = True
            eng.add_walls(method="custom", pos=walls.tolist())
        eng.add_agents(self._handle, method="custom", pos=agents.tolist())
        if self._opp_handle is not None and len(opponents):
            eng.add_agents(self._opp_handle, method="custom", pos=opponents.tolist())
        ids = eng.get_agent_id(self._handle)
        self.agents = self.possible_agents[: len(ids)]
        self._id_to_name = {int(i): name for i, name in zip(ids, self.agents, strict=True)}
        self._steps = 0
        obs, _, _ = self._observe()
        return obs, {a: {} for a in self.agents}

    def step(
        self, actions: dict[str, int]
    ) -> tuple[
        dict[str, np.ndarray],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict],
    ]:
        """One engine step; agents without an action stay where they are."""
        eng = self._engine
        ids = eng.get_agent_id(self._handle)
        act = np.array(
            [actions.get(self._id_to_name[int(i)], self.stay_action) for i in ids], dtype=np.int32
        )
        if act.size and (act.min() < 0 or act.max() >= self._act_space.n):
            raise ValueError(f"actions must lie in 0..{self._act_space.n - 1}, got {act.tolist()}")
        eng.set_action(self._handle, act)
        if self._opp_handle is not None and eng.get_num(self._opp_handle):
            eng.set_action(self._opp_handle, self._opponent_actions())
        done = eng.step()
        self._steps += 1

        obs, rewards, alive = self._observe()
        eng.clear_dead()
        terminated = {a: done or not alive.get(a, False) for a in self.agents}
        out_of_time = self._steps >= self.max_steps
        truncated = {a: out_of_time and not terminated[a] for a in self.agents}
        infos = {a: {} for a in self.agents}
        self.agents = [a for a in self.agents if not (terminated[a] or truncated[a])]
        return obs, rewards, terminated, truncated, infos

    def state(self) -> np.ndarray:
        """Global state: whole-map planes pooled to at most ``STATE_GRID`` cells a side, + time.

        Planes are walls, then presence and hp / max hp of each group (learning group first),
        averaged over ``block x block`` cells (padding counts as wall); the last entry is the
        elapsed fraction of ``max_steps``.
        """
        eng = self._engine
        handles = [h for h in (self._handle, self._opp_handle) if h is not None]
        planes = np.zeros((1 + 2 * len(handles), self.map_size, self.map_size), dtype=np.float32)
        planes[0] = self._walls
        for k, h in enumerate(handles):
            if not eng.get_num(h):
                continue
            view, _ = eng.get_observation(h)
            c = view.shape[1] // 2
            x, y = eng.get_pos(h).T
            planes[1 + 2 * k, x, y] = 1.0
            planes[2 + 2 * k, x, y] = view[:, c, c, 2]
        side = self._state_grid * self._block
        pad = side - self.map_size
        padded = np.pad(planes, ((0, 0), (0, pad), (0, pad)))
        padded[0, self.map_size :, :] = padded[0, :, self.map_size :] = 1.0
        g, b = self._state_grid, self._block
        pooled = padded.reshape(len(planes), g, b, g, b).mean(axis=(2, 4))
        return np.append(pooled.ravel(), self._steps / self.max_steps).astype(np.float32)

    def render(self) -> str | None:
        """ASCII map (``#`` wall, ``A`` learning agent, ``o`` opponent) when render_mode="ansi"."""
        if self.render_mode is None:
            return None
        grid = np.where(self._walls, "#", ".")
        for h, ch in ((self._opp_handle, "o"), (self._handle, "A")):
            if h is not None and self._engine.get_num(h):
                x, y = self._engine.get_pos(h).T
                grid[x, y] = ch
        return "\n".join("".join(row) for row in grid.T)

    def close(self) -> None:
        """Nothing to release: the engine is freed with the env."""

    # ----- internals -----------------------------------------------------------------------

    def _draw_layout(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = int(self._rng.integers(self.agent_range[0], self.agent_range[1] + 1))
        n_walls = int(self._rng.integers(self.obstacle_range[0], self.obstacle_range[1] + 1))
        n_opp = self._n_opponents(n)
        inner = self.map_size - 2
        cells = self._rng.choice(inner * inner, size=n + n_opp + n_walls, replace=False)
        xy = np.stack([cells % inner, cells // inner], axis=1) + 1
        return xy[:n], xy[n : n + n_opp], xy[n + n_opp :]

    def _check_layout(self, layout: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        parts = []
        for key in ("agents", "opponents", "walls"):
            pos = np.asarray(layout.get(key, []), dtype=np.int64).reshape(-1, 2)
            if len(pos) and (pos.min() < 1 or pos.max() > self.map_size - 2):
                raise EnvConfigError(f"layout {key}: cells must lie inside the border wall")
            parts.append(pos)
        agents, opponents, walls = parts
        if not 1 <= len(agents) <= self.agent_range[1]:
            raise EnvConfigError(f"layout: 1 to {self.agent_range[1]} agents, got {len(agents)}")
        if len(opponents) and self._opp_handle is None:
            raise EnvConfigError("layout: this scenario has no opponents")
        every = np.concatenate(parts)
        if len(np.unique(every, axis=0)) != len(every):
            raise EnvConfigError("layout: two things on one cell")
        return agents, opponents, walls

    def _observe(self) -> tuple[dict[str, np.ndarray], dict[str, float], dict[str, bool]]:
        """Observation, engine reward and alive flag of every present learning agent."""
        eng, h = self._engine, self._handle
        ids = eng.get_agent_id(h)
        view, feat = eng.get_observation(h)
        pos = eng.get_pos(h) / (self.map_size - 1)
        flat = np.concatenate([view.reshape(len(ids), -1), feat, pos], axis=1, dtype=np.float32)
        names = [self._id_to_name[int(i)] for i in ids]
        obs = dict(zip(names, flat, strict=True))
        zero = np.zeros(self.obs_size, dtype=np.float32)
        rewards = dict(zip(names, eng.get_reward(h).tolist(), strict=True))
        alive = dict(zip(names, eng.get_alive(h).tolist(), strict=True))
        present = self.agents
        return (
            {a: obs.get(a, zero) for a in present},
            {a: float(rewards.get(a, 0.0)) for a in present},
            {a: alive.get(a, False) for a in present},
        )

    def _opponent_actions(self) -> np.ndarray:
        """Scripted opponents' actions, in engine order (default: uniform random moves)."""
        n = self._engine.get_num(self._opp_handle)
        n_moves = len(move_offsets(self.opponent_attrs["speed"]))
        return self._rng.integers(n_moves, size=n).astype(np.int32)


class PursuitEnv(MagentEnv):
    """Cooperative pursuit (Table I): wolves (learning) score by attacking fleeing sheep.

    As many sheep as wolves (the paper varies both together). Wolves attack with damage 0, so a
    sheep is never killed and a trapped sheep keeps paying. The sheep's speed 1.5 is exact in
    MAgent2's terms: speed is the radius of the move circle, so a sheep steps to any of its 8
    neighbours (diagonals included) while a wolf (speed 1) steps to 4.

    ``prey_alertness`` (1, the task, by default) is the chance, drawn per sheep and step, that a
    sheep that sees a wolf flees rather than wanders; below 1 it makes a training curriculum
    (``udan-train --prey-curriculum``), as MAgent's own pursuit trains its prey from random.
    """

    def __init__(self, name: str, *, prey_alertness: float = 1.0, **kwargs: Any) -> None:
        self.prey_alertness = prey_alertness
        super().__init__(name, **kwargs)

    @property
    def prey_alertness(self) -> float:
        return self._prey_alertness

    @prey_alertness.setter
    def prey_alertness(self, value: float) -> None:
        if not 0.0 <= value <= 1.0:
            raise EnvConfigError(f"prey_alertness must lie in [0, 1], got {value}")
        self._prey_alertness = float(value)

    default_map_size = 100
    default_max_steps = 300
    default_prey_per_agent = 1.0
    agent_attrs: ClassVar[dict[str, Any]] = {
        "view": 5, "attack": 2, "speed": 1, "hp": 1, "damage": 0, "attack_penalty": -0.2,
    }  # fmt: skip
    opponent_attrs: ClassVar[dict[str, Any]] = {"view": 4, "attack": 0, "speed": 1.5, "hp": 1}

    def _reward_rules(self, cfg: gw.Config, group: int, opp: int | None) -> None:
        wolf, sheep = gw.AgentSymbol(group, index="any"), gw.AgentSymbol(opp, index="any")
        cfg.add_reward_rule(gw.Event(wolf, "attack", sheep), receiver=[wolf, sheep], value=[1, -1])

    def _opponent_actions(self) -> np.ndarray:
        """Each sheep moves to the free neighbour cell farthest from the wolves it sees.

        "Farthest" maximises the distance to the nearest wolf within view range 4; a sheep that
        sees no wolf (or, below full ``prey_alertness``, is not alert this step) moves at random.
        Ties are broken at random.
        """
        wolves, sheep = self.positions()
        moves = move_offsets(self.opponent_attrs["speed"])
        cand = sheep[:, None, :] + moves[None, :, :]  # (sheep, move, xy)
        blocked = self._walls.copy()
        blocked[wolves[:, 0], wolves[:, 1]] = True
        blocked[sheep[:, 0], sheep[:, 1]] = True
        free = ~blocked[cand[..., 0], cand[..., 1]]
        free[:, np.flatnonzero((moves == 0).all(1))] = True
        near = np.linalg.norm(sheep[:, None, :] - wolves[None, :, :], axis=2)  # (sheep, wolf)
        seen = near <= self.opponent_attrs["view"]
        dist = np.linalg.norm(cand[:, :, None, :] - wolves[None, None, :, :], axis=3)
        dist = np.where(seen[:, None, :], dist, np.inf).min(axis=2)  # (sheep, move)
        noise = self._rng.random(dist.shape)
        flee = np.where(free, np.where(np.isinf(dist), 0.0, dist) + 1e-3 * noise, -np.inf)
        wander = self._rng.integers(len(moves), size=len(sheep))
        fleeing = seen.any(axis=1)
        if self.prey_alertness < 1.0:  # drawn only then: the task's sheep play as they always did
            fleeing &= self._rng.random(len(sheep)) < self.prey_alertness
        return np.where(fleeing, flee.argmax(axis=1), wander).astype(np.int32)


class TigerEnv(MagentEnv):
    """Cooperative tiger (Table III): a tiger scores only when attacking a deer with another one.

    MAgent2 reward rule (as in its tiger_deer): ``attack(a, deer) & attack(b, deer)`` for two
    "any" tigers pays each 1/2 per matching ordered pair, so two tigers hitting one deer in the
    same step get 1 each and a lone attacker gets 0. With k tigers on one deer each gets k - 1
    (one per partner): the engine counts pairs, the paper does not say. A deer dies at 0 hp
    (damage 1 per hit, +0.2 hp per step) and is removed; the engine pays nothing for the hit
    that kills. Tigers cannot be hurt (deer have no attack), so they never die. When every deer
    is dead the engine declares game over (nothing can be earned any more): the episode ends.

    Deer count: 5 per tiger (``prey_per_agent``), MAgent2's tiger_deer density ratio, so a
    tiger in view range 4 usually has a deer in sight; deer move at random.
    """

    default_map_size = 50
    default_max_steps = 200
    default_prey_per_agent = 5.0
    agent_attrs: ClassVar[dict[str, Any]] = {
        "view": 4, "attack": 1, "speed": 1, "hp": 8, "step_recover": 0, "damage": 1,
    }  # fmt: skip
    opponent_attrs: ClassVar[dict[str, Any]] = {
        "view": 1, "attack": 0, "speed": 1, "hp": 5, "step_recover": 0.2,
    }  # fmt: skip

    def _reward_rules(self, cfg: gw.Config, group: int, opp: int | None) -> None:
        a, b = gw.AgentSymbol(group, index="any"), gw.AgentSymbol(group, index="any")
        deer = gw.AgentSymbol(opp, index="any")
        both = gw.Event(a, "attack", deer) & gw.Event(b, "attack", deer)
        cfg.add_reward_rule(both, receiver=[a, b], value=[0.5, 0.5])


class QueueEnv(MagentEnv):
    """Cooperative queue: agents pay 0.2 per step until they all stand in one line.

    The step cost is MAgent2's ``step_reward``. "Lined up" is MAgent2's ``in_a_line`` event over
    the whole group: every agent in one column (or one row) spanning exactly N consecutive cells,
    i.e. contiguous; a single agent always is. Each step it holds, every agent gets +1. The rule
    is terminal by default, so the episode ends at the first line (the paper's "as soon as
    possible"); ``end_when_lined_up=False`` keeps it running, paying +1 every step the line holds.
    """

    default_map_size = 30
    default_max_steps = 300
    agent_attrs: ClassVar[dict[str, Any]] = {
        "view": 5, "attack": 0, "speed": 1, "hp": 1, "step_reward": -0.2,
    }  # fmt: skip

    def __init__(self, name: str, end_when_lined_up: bool = True, **kwargs: Any) -> None:
        self.end_when_lined_up = bool(end_when_lined_up)
        super().__init__(name, **kwargs)
        if self.agent_range[1] > self.map_size - 2:
            raise EnvConfigError(
                f"{name}: {self.agent_range[1]} agents cannot line up in a "
                f"{self.map_size}x{self.map_size} map (at most {self.map_size - 2})"
            )

    def potential(self) -> dict[str, float]:
        """Each engine-held agent's step cost of the cells it still has to walk to the nearest
        line: ``step_reward · d``, 0 for a fleet in line.

        The nearest line is the column (or row) and first cell that the fleet, sorted along it,
        reaches with the fewest moves in all (median across, median of the sorted offsets
        along); ``d`` is this agent's L1 distance to its cell there. It ignores that agents
        block each other, so the fleet's total is a lower bound on its moves left, never a
        plan (one agent's ``d`` can jump when the nearest line changes). Training's reward
        shaping (``udan-train --shaping``) reads it; the task's rewards never do."""
        cost = float(self.agent_attrs["step_reward"])
        return {name: cost * walk for name, walk in self.line_walk().items()}

    def line_walk(self) -> dict[str, float]:
        """Each engine-held agent's L1 distance to its cell in the nearest line (see
        :meth:`potential`)."""
        cells = self.agent_cells()
        if not cells:
            return {}
        xy = np.array(list(cells.values()), dtype=np.int64)
        column, row = line_distances(xy, self.map_size), line_distances(xy[:, ::-1], self.map_size)
        best = row if row.sum() < column.sum() else column
        return dict(zip(cells, best.astype(float).tolist(), strict=True))

    def _reward_rules(self, cfg: gw.Config, group: int, opp: int | None) -> None:
        everyone = gw.AgentSymbol(group, index="all")
        cfg.add_reward_rule(
            gw.Event(everyone, "in_a_line"),
            receiver=everyone,
            value=1.0,
            terminal=self.end_when_lined_up,
        )


def line_distances(cells: np.ndarray, map_size: int) -> np.ndarray:
    """L1 distance of each ``(x, y)`` cell to its place in the nearest column of ``len(cells)``
    contiguous cells inside the map's walls: the column at the median x, the agents in y order
    on consecutive cells from the median of their sorted y minus rank (what minimises the total
    of the moves along, for cells taken in that order), clipped to fit the map."""
    n = len(cells)
    inner = (1, map_size - 2)
    column = int(np.clip(np.median(cells[:, 0]).round(), *inner))
    order = np.argsort(cells[:, 1], kind="stable")
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    offsets = cells[order, 1] - np.arange(n)
    first = int(np.clip(np.median(offsets).round(), inner[0], inner[1] - n + 1))
    return np.abs(cells[:, 0] - column) + np.abs(cells[:, 1] - (first + rank))


_SCENARIOS: dict[str, type[MagentEnv]] = {
    "magent/pursuit": PursuitEnv,
    "magent/tiger": TigerEnv,
    "magent/queue": QueueEnv,
}


def make(name: str, **kwargs: Any) -> MagentEnv:
    """The MAgent scenario ``name``; kwargs: agents, obstacles, seed, max_steps, map_size, ...

    Pursuit and tiger also take ``prey_per_agent``; queue takes ``end_when_lined_up``.
    """
    if name not in _SCENARIOS:
        raise EnvConfigError(f"unknown MAgent scenario {name!r}; known: {', '.join(_SCENARIOS)}")
    cls = _SCENARIOS[name]
    known = {
        p
        for c in cls.__mro__
        if "__init__" in vars(c) and issubclass(c, MagentEnv)
        for p in signature(c.__init__).parameters
    } - {"self", "name", "kwargs"}
    unknown = sorted(set(kwargs) - known)
    if unknown:
        raise EnvConfigError(
            f"{name}: unknown option(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}"
        )
    return cls(name, **kwargs)


@dataclass(frozen=True)
class MagentBatchConfig:
    """What the learner and ``udan-eval`` read of a batch's task (as of an arena's config)."""

    name: str
    agents: tuple[int, int]
    obstacles: tuple[int, int]
    max_steps: int
    map_size: int


class MagentBatch:
    """B MAgent scenario episodes behind the arena core's interface (:class:`ArenaBatch`), so
    ``udan-train``, ``udan-eval`` and the replay treat them alike.

    Slot i of an episode is PettingZoo's ``agent_i``. An agent the engine removes, and every
    agent once the engine declares game over, is absent from the next step on: zero
    observation, no reward, ``present`` False, so the replay masks it and nothing bootstraps
    from it. At the time limit agents stay present (the learner bootstraps through it, as in the
    arena). An episode that is over idles, absent and unrewarded, until the time limit, so every
    episode of a batch has ``max_steps`` steps; ``done`` says which are over. Each reset seeds
    its env from :attr:`rng`, so the batch's whole future is a function of that generator's
    state (exact resume).
    """

    def __init__(
        self, name: str, batch: int, seed: int | np.random.SeedSequence | None = 0, **options: Any
    ) -> None:
        if batch < 1:
            raise EnvConfigError(f"batch must be >= 1, got {batch}")
        self.envs = [make(name, **options) for _ in range(batch)]
        first = self.envs[0]
        self.spec = first.spec()
        self.n_actions = len(self.spec.actions)
        self.config = MagentBatchConfig(
            name, first.agent_range, first.obstacle_range, first.max_steps, first.map_size
        )
        self.batch, self.slots = batch, first.agent_range[1]
        self.has_opponents = first.opponent_attrs is not None
        self.rng = np.random.default_rng(seed)
        b, n = batch, self.slots
        self.pos = np.zeros((b, n, 2), dtype=np.int64)
        self.present = np.zeros((b, n), dtype=bool)
        self.joined = np.zeros((b, n), dtype=bool)
        self.episode_return = np.zeros((b, n), dtype=np.float32)
        self.target_score = np.zeros(b, dtype=np.float32)  # no target here: 0 (udan-eval reads it)
        self.t = np.zeros(b, dtype=np.int64)
        self.over = np.zeros(b, dtype=bool)
        self._obs = np.zeros((b, n, self.spec.size), dtype=np.float32)
        self._names = first.possible_agents

    def reset(self, where: np.ndarray | None = None) -> np.ndarray:
        """Start new episodes in the envs selected by the bool mask ``where`` (default all)."""
        idx = np.arange(self.batch) if where is None else np.flatnonzero(where)
        for b in idx:
            obs, _ = self.envs[b].reset(seed=int(self.rng.integers(2**63 - 1)))
            self.present[b] = False
            self._obs[b] = 0.0
            for name, row in obs.items():
                slot = self._names.index(name)
                self.present[b, slot] = True
                self._obs[b, slot] = row
            self.joined[b] = self.present[b]
            self.episode_return[b] = 0.0
            self.t[b] = 0
            self.over[b] = False
            self._read_cells(b)
        return self.observe()

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One action per slot (ignored for absent slots); a step past the time limit is an
        error. Returns (observations (B, N, D), rewards (B, N), done (B,))."""
        if (self.t >= self.config.max_steps).any():
            first = np.flatnonzero(self.t >= self.config.max_steps)[0]
            raise ValueError(f"episode over in env {first}: reset it first")
        actions = np.asarray(actions)
        if actions.shape != (self.batch, self.slots) or actions.dtype.kind not in "iu":
            raise ValueError(f"actions must be integers shaped {(self.batch, self.slots)}")
        chosen = actions[self.present]
        if chosen.size and (chosen.min() < 0 or chosen.max() >= self.n_actions):
            raise ValueError(f"actions must lie in 0..{self.n_actions - 1}")
        reward = np.zeros((self.batch, self.slots), dtype=np.float32)
        self.joined[:] = False
        for b in np.flatnonzero(~self.over):
            slots = np.flatnonzero(self.present[b])
            names = [self._names[i] for i in slots]
            obs, rewards, terminated, _, _ = self.envs[b].step(
                {name: int(actions[b, i]) for name, i in zip(names, slots, strict=True)}
            )
            for name, i in zip(names, slots, strict=True):
                reward[b, i] = rewards[name]
                self.present[b, i] = not terminated[name]
                self._obs[b, i] = obs[name] if self.present[b, i] else 0.0
            self.over[b] = not self.present[b].any()
            self._read_cells(b)
        self.t += 1
        self.episode_return += reward
        return self.observe(), reward, self.over | (self.t >= self.config.max_steps)

    def _read_cells(self, b: int) -> None:
        for name, cell in self.envs[b].agent_cells().items():
            self.pos[b, self._names.index(name)] = cell

    @property
    def prey_alertness(self) -> float:
        """Pursuit's :attr:`PursuitEnv.prey_alertness`, the same in every env of the batch."""
        return self.envs[0].prey_alertness

    @prey_alertness.setter
    def prey_alertness(self, value: float) -> None:
        if not hasattr(self.envs[0], "prey_alertness"):
            raise EnvConfigError(f"{self.config.name} has no prey whose alertness could be set")
        for env in self.envs:
            env.prey_alertness = value

    def potential(self) -> np.ndarray:
        """Every slot's :meth:`MagentEnv.potential` (B, N); absent slots and episodes that are
        over are 0 (a terminal state's potential, so shaping stays policy-invariant)."""
        return self._per_slot("potential")

    def line_walk(self) -> np.ndarray:
        """Queue: every slot's :meth:`QueueEnv.line_walk` (B, N), 0 where absent or over."""
        return self._per_slot("line_walk")

    def _per_slot(self, method: str) -> np.ndarray:
        out = np.zeros((self.batch, self.slots), dtype=np.float32)
        for b in np.flatnonzero(~self.over):
            for name, value in getattr(self.envs[b], method)().items():
                out[b, self._names.index(name)] = value
        return np.where(self.present, out, 0.0).astype(np.float32)

    def observe(self) -> np.ndarray:
        """Every slot's observation (B, N, spec.size); absent slots are zero."""
        return self._obs.copy()

    def global_state(self) -> np.ndarray:
        """Each env's :meth:`MagentEnv.state` (B, S), for QMIX's mixer and COMA's critic."""
        return np.stack([env.state() for env in self.envs])


def make_batch(
    name: str, batch: int, seed: int | np.random.SeedSequence | None = 0, **options: Any
) -> MagentBatch:
    """Registry factory: ``magent/<scenario>`` -> :class:`MagentBatch` of ``batch`` envs."""
    return MagentBatch(name, batch=batch, seed=seed, **options)
