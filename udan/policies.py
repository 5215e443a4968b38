"""Reference policies: the floor (``random``, every task), the arena's ceiling (``oracle``), and
MAgent's scripted references: ``chaser`` (pursuit, tiger) and ``liner`` (queue), below.

The oracle is a centralised planner with the whole map, obeying the same world rules:

- find_water: agents are assigned to the drinking cells by minimum total shortest-path length,
  then planned one after another through space-time (cells and swaps reserved by the agents
  already planned, a goal held for the rest of the episode once reached); several priority
  orders are tried and the one with the highest planned score is kept. Its plan executes
  exactly under :func:`udan.envs.rules.resolve_moves`.
- hidden_goal: every agent walks straight into the goal's zone (nothing blocks a walk there).
- surround: every step the target's flight is predicted where its rule forces it (a unique best
  move), each agent is assigned one side of that cell (minimum total distance) and moves
  greedily along the shortest path, in order of distance, never into a cell another agent
  holds or claims, so it can follow the target into the cell the target leaves.
"""

from __future__ import annotations

import itertools
from typing import Protocol

import numpy as np

from udan.envs.arena import ArenaBatch
from udan.envs.rules import ACTION_DELTAS, FREE, N_ACTIONS, WAIT, WATER

_OPPOSITE = np.array([1, 0, 3, 2, 4])


class Policy(Protocol):
    """Acts for every slot of every arena of a batch."""

    def reset(self, env: ArenaBatch) -> None: ...

    def act(self, env: ArenaBatch) -> np.ndarray: ...


class RandomPolicy:
    """Uniform random actions: the floor every learned policy must beat."""

    def __init__(self, seed: int | None = 0) -> None:
        self.rng = np.random.default_rng(seed)

    def reset(self, env: ArenaBatch) -> None:
        """Nothing to plan."""

    def act(self, env: ArenaBatch) -> np.ndarray:
        n_actions = getattr(env, "n_actions", N_ACTIONS)  # a MAgent batch has its own count
        return self.rng.integers(0, n_actions, size=(env.batch, env.slots))


def walk_to_zone(pos: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Actions (B, N) that bring agents at ``pos`` (B, N, 2) one step nearer to within one cell
    (Manhattan) of ``goal`` (B, N or 1, 2) on an empty arena: rows first, then columns; wait
    once there."""
    d_row, d_col = (goal - pos)[..., 0], (goal - pos)[..., 1]
    there = np.abs(d_row) + np.abs(d_col) <= 1
    by_row = np.where(d_row < 0, 0, 1)  # up, down
    by_col = np.where(d_col < 0, 2, 3)  # left, right
    return np.where(there, WAIT, np.where(d_row != 0, by_row, by_col))


def distance_fields(passable: np.ndarray, goals: list[tuple[int, int]]) -> np.ndarray:
    """Shortest-path length from every cell to each goal (S, H, W) through ``passable`` cells.

    One breadth-first search for all goals at once, as boolean dilation; inf where unreachable.
    """
    h, w = passable.shape
    dist = np.full((len(goals), h, w), np.inf)
    frontier = np.zeros((len(goals), h + 2, w + 2), dtype=bool)
    for i, (r, c) in enumerate(goals):
        frontier[i, r + 1, c + 1] = True
        dist[i, r, c] = 0
    step = 0
    while frontier.any():
        step += 1
        grown = (
            frontier[:, :-2, 1:-1]
            | frontier[:, 2:, 1:-1]
            | frontier[:, 1:-1, :-2]
            | frontier[:, 1:-1, 2:]
        )
        fresh = grown & passable[None] & np.isinf(dist)
        dist[fresh] = step
        frontier[:, 1:-1, 1:-1] = fresh
    return dist


def distance_field(passable: np.ndarray, goal: tuple[int, int]) -> np.ndarray:
    """Shortest-path length from every cell to ``goal`` (inf if unreachable)."""
    return distance_fields(passable, [goal])[0]


def assign(cost: np.ndarray) -> list[int]:
    """Goal index per agent minimising the total cost; agents beyond the goals reuse goals.

    Exhaustive over permutations (the arena has at most a handful of agents per task), greedy
    for the agents that do not get a goal of their own.
    """
    n_agents, n_goals = cost.shape
    capped = np.minimum(cost, 1e6)
    best, best_cost = None, np.inf
    k = min(n_agents, n_goals)
    for agents in itertools.combinations(range(n_agents), k):
        for goals in itertools.permutations(range(n_goals), k):
            total = capped[list(agents), list(goals)].sum()
            if total < best_cost:
                best, best_cost = dict(zip(agents, goals, strict=True)), total
    return [best[a] if a in best else int(np.argmin(capped[a])) for a in range(n_agents)]


def _shift(mask: np.ndarray, d_row: int, d_col: int) -> np.ndarray:
    """``out[r + d_row, c + d_col] = mask[r, c]`` inside the grid."""
    out = np.zeros_like(mask)
    h, w = mask.shape
    out[max(d_row, 0) : h + min(d_row, 0), max(d_col, 0) : w + min(d_col, 0)] = mask[
        max(-d_row, 0) : h + min(-d_row, 0), max(-d_col, 0) : w + min(-d_col, 0)
    ]
    return out


class _Reservations:
    """Cells and moves taken by the agents planned so far, over a horizon of ``steps``."""

    def __init__(self, steps: int, shape: tuple[int, int]) -> None:
        self.cells = np.zeros((steps + 1, *shape), dtype=bool)
        self.moves = np.zeros((steps, N_ACTIONS, *shape), dtype=bool)  # forbidden (t, dir, src)

    def add(self, start: tuple[int, int], actions: list[int]) -> None:
        r, c = start
        self.cells[0, r, c] = True
        for t, a in enumerate(actions):
            nr, nc = r + ACTION_DELTAS[a][0], c + ACTION_DELTAS[a][1]
            if a != WAIT:
                self.moves[t, _OPPOSITE[a], nr, nc] = True  # the swap back is forbidden
            r, c = nr, nc
            self.cells[t + 1, r, c] = True


def plan_path(
    passable: np.ndarray,
    start: tuple[int, int],
    goal: tuple[int, int],
    taken: _Reservations,
    steps: int,
) -> tuple[list[int], int]:
    """Earliest conflict-free arrival at ``goal`` (held afterwards) in space-time.

    Returns (actions for ``steps`` steps, arrival time or ``steps + 1`` when unreachable, in
    which case the agent gets as close as it can).
    """
    reach = np.zeros((steps + 1, *passable.shape), dtype=bool)
    parent = np.full((steps + 1, *passable.shape), -1, dtype=np.int8)
    reach[0][start] = True
    # goal usable from t on iff no reservation on it at any t' >= t
    goal_free = ~np.flip(np.logical_or.accumulate(np.flip(taken.cells[:, goal[0], goal[1]])))
    arrival = 0 if goal_free[0] and start == goal else -1
    for t in range(steps):
        if arrival >= 0:
            break
        for a in range(N_ACTIONS):
            src = reach[t] & ~taken.moves[t, a]
            dst = _shift(src, *ACTION_DELTAS[a]) & passable & ~taken.cells[t + 1]
            fresh = dst & ~reach[t + 1]
            parent[t + 1][fresh] = a
            reach[t + 1] |= dst
        if reach[t + 1][goal] and goal_free[t + 1]:
            arrival = t + 1
    if arrival >= 0:
        end, end_t = goal, arrival
    else:  # unreachable: the reachable state closest to the goal, as late as possible
        dist = distance_field(passable, goal)
        end_t = int(np.flatnonzero(reach.reshape(steps + 1, -1).any(1))[-1])
        cells = np.argwhere(reach[end_t])
        end = tuple(cells[np.argmin(dist[cells[:, 0], cells[:, 1]])])
    actions = []
    cell = end
    for t in range(end_t, 0, -1):
        a = int(parent[t][cell])
        actions.append(a)
        cell = (cell[0] - ACTION_DELTAS[a][0], cell[1] - ACTION_DELTAS[a][1])
    actions.reverse()
    actions += [WAIT] * (steps - len(actions))
    return actions, arrival if arrival >= 0 else steps + 1


class OraclePolicy:
    """Centralised planner with the full map: the ceiling for learned policies."""

    def __init__(self, seed: int | None = 0, orders: int = 6) -> None:
        self.rng = np.random.default_rng(seed)
        self.orders = orders
        self._plans: dict[int, dict[int, list[int]]] = {}

    def reset(self, env: ArenaBatch) -> None:
        self._plans = {}

    def act(self, env: ArenaBatch) -> np.ndarray:
        if env.config.task == "find_water":
            return self._act_find_water(env)
        if env.config.task == "hidden_goal":
            return walk_to_zone(env.pos, env.goal[:, None])
        return self._act_surround(env)

    # ------------------------------------------------------------------ find_water
    def _act_find_water(self, env: ArenaBatch) -> np.ndarray:
        actions = np.full((env.batch, env.slots), WAIT, dtype=np.int64)
        for b in range(env.batch):
            plan = self._plans.get(b)
            if (
                plan is None
                or env.joined[b].any()
                or env.left[b].any()
                or (set(plan) != set(np.flatnonzero(env.present[b])))
            ):
                plan = self._plans[b] = self._plan_find_water(env, b)
            for slot, steps in plan.items():
                if steps:
                    actions[b, slot] = steps.pop(0)
        return actions

    def _plan_find_water(self, env: ArenaBatch, b: int) -> dict[int, list[int]]:
        cfg = env.config
        passable = env.layout[b] == FREE
        slots = [int(s) for s in np.flatnonzero(env.present[b])]
        starts = [tuple(int(v) for v in env.pos[b, s]) for s in slots]
        goals = [(1, int(c)) for c in np.flatnonzero(env.layout[b, 0] == WATER)]
        fields = distance_fields(passable, goals)
        cost = np.array([[f[s] for f in fields] for s in starts])
        goal_of = assign(cost)
        steps = int(cfg.max_steps - env.t[b])
        by_distance = sorted(range(len(slots)), key=lambda i: -cost[i, goal_of[i]])
        orders = [by_distance, by_distance[::-1]]
        orders += [list(self.rng.permutation(len(slots))) for _ in range(self.orders - 2)]
        best, best_score = {}, -1
        for order in orders:
            taken = _Reservations(steps, passable.shape)
            plan, score = {}, 0
            for i in order:
                acts, arrival = plan_path(passable, starts[i], goals[goal_of[i]], taken, steps)
                taken.add(starts[i], acts)
                plan[slots[i]] = acts
                score += max(steps - max(arrival, 1) + 1, 0)
            if score > best_score:
                best, best_score = plan, score
        return best

    # ------------------------------------------------------------------ surround
    def _act_surround(self, env: ArenaBatch) -> np.ndarray:
        actions = np.full((env.batch, env.slots), WAIT, dtype=np.int64)
        h, w = env.config.height, env.config.width
        flee = env.flee_scores()
        for b in range(env.batch):
            slots = [int(s) for s in np.flatnonzero(env.present[b])]
            # Predict the target. Unseen agents leave it wandering at random: approach its
            # cell. Fleeing with one best move: surround that cell. Fleeing with ties: the cell
            # it leaves is the one sure to be next to it afterwards (following is allowed), so
            # that goal is preferred, the others flank its possible destinations.
            here = tuple(int(v) for v in env.target[b])
            best = np.flatnonzero(flee[b] == flee[b].max())
            fleeing = flee[b].max() > 0 and WAIT not in best
            ends = [env.target[b] + ACTION_DELTAS[a] for a in best] if fleeing else [env.target[b]]
            passable = env.layout[b] == FREE
            passable[here] = fleeing
            for end in ends:
                passable[tuple(end)] = False
            sides = {tuple(int(v) for v in end + d) for end in ends for d in ACTION_DELTAS[:4]}
            sides = sorted(s for s in sides if 0 <= s[0] < h and 0 <= s[1] < w and passable[s])
            if not sides:
                continue
            fields = distance_fields(passable, sides)
            pos = {s: tuple(int(v) for v in env.pos[b, s]) for s in slots}
            cost = np.array([[f[pos[s]] for f in fields] for s in slots])
            if fleeing and len(ends) > 1:
                cost[:, sides.index(here)] -= 0.5
            goal_of = dict(zip(slots, assign(cost), strict=True))
            undecided = set(pos.values())
            claimed: set[tuple[int, int]] = set()
            moving_from: dict[tuple[int, int], tuple[int, int]] = {}
            for s in sorted(slots, key=lambda s: cost[slots.index(s), goal_of[s]]):
                here = pos[s]
                undecided.discard(here)
                field = fields[goal_of[s]]
                best_a, best_d = WAIT, field[here]
                for a in range(4):
                    nxt = (here[0] + ACTION_DELTAS[a][0], here[1] + ACTION_DELTAS[a][1])
                    if not (0 <= nxt[0] < h and 0 <= nxt[1] < w) or not passable[nxt]:
                        continue
                    if nxt in claimed or nxt in undecided or moving_from.get(nxt) == here:
                        continue
                    if field[nxt] < best_d:
                        best_a, best_d = a, field[nxt]
                nxt = (here[0] + ACTION_DELTAS[best_a][0], here[1] + ACTION_DELTAS[best_a][1])
                claimed.add(nxt)
                moving_from[here] = nxt
                actions[b, s] = best_a
        return actions


class ChaserPolicy:
    """MAgent pursuit and tiger, scripted and decentralised: each agent sees what its view shows
    and nothing else, and no messages pass.

    An agent attacks the nearest opponent it sees when that one is in attack range; otherwise it
    steps toward it along the longer axis of the gap (the other axis when that cell is taken, a
    random one on a tie); seeing none, it walks a straight line in a heading it keeps until it is
    blocked or, with probability 1/20 a step, draws anew. A reference for what the task gives
    without learning or communication, not an optimum.
    """

    turn = 0.05

    def __init__(self, seed: int | None = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self._heading: np.ndarray | None = None

    def reset(self, env) -> None:
        self._heading = self.rng.integers(0, 4, size=(env.batch, env.slots))

    def act(self, env) -> np.ndarray:
        if not getattr(env, "has_opponents", False):
            raise ValueError("the chaser plays MAgent tasks with opponents (pursuit, tiger)")
        assert self._heading is not None, "reset first"
        return _per_world(env, lambda b, world: self.act_in(world, self._heading[b]))

    def act_in(self, world, heading: np.ndarray) -> dict[str, int]:
        """Actions of one MAgent env's agents by name; ``heading`` (by slot) is kept in place."""
        view, reach = float(world.agent_attrs["view"]), float(world.agent_attrs["attack"])
        steps = _unit_moves(world)
        agents, opponents = world.positions()
        taken = {tuple(c) for c in agents.tolist()} | {tuple(c) for c in opponents.tolist()}
        out = {}
        for name, cell in world.agent_cells().items():
            gap = opponents - cell
            dist = np.hypot(gap[:, 0], gap[:, 1])
            if len(dist) and dist.min() <= view:
                dx, dy = (int(v) for v in gap[int(dist.argmin())])
                if dist.min() <= reach:
                    out[name] = world.attack_action(dx, dy)
                    continue
                along_x = abs(dx) > abs(dy) or (abs(dx) == abs(dy) and self.rng.random() < 0.5)
                order = [(int(np.sign(dx)), 0), (0, int(np.sign(dy)))]
                options = [d for d in (order if along_x else order[::-1]) if d != (0, 0)]
                free = [d for d in options if (cell[0] + d[0], cell[1] + d[1]) not in taken]
                out[name] = steps[_STEPS.index((free or options)[0])]
                continue
            slot = world.possible_agents.index(name)
            dx, dy = _STEPS[heading[slot]]
            ahead = (cell[0] + dx, cell[1] + dy)
            if self.rng.random() < self.turn or ahead in taken or world.walls[ahead]:
                heading[slot] = self.rng.integers(0, 4)
            out[name] = steps[heading[slot]]
        return out


class LinerPolicy:
    """MAgent queue, scripted and decentralised: each agent reads its own cell (its observation
    carries it) and the four cells beside it, and no messages pass.

    An agent steps west while it can; at the west wall it steps south until the cell below is
    taken, so the agents stack up from the south-west corner into one contiguous column, which is
    the queue's line. An agent whose west cell another agent holds steps north (the stack's open
    end), or waits. A reference for what the task gives without learning or communication, not
    an optimum; it refuses a map with walls inside (the task has none by default).
    """

    def __init__(self, seed: int | None = 0) -> None:
        del seed  # deterministic; the argument keeps the policies' one constructor

    def reset(self, env) -> None:
        """Nothing to plan."""

    def act(self, env) -> np.ndarray:
        if getattr(env, "has_opponents", True):
            raise ValueError("the liner plays MAgent queue (agents without opponents)")
        if any(world.walls[1:-1, 1:-1].any() for world in env.envs):
            raise ValueError("the liner lines up along a wall: it needs a map without inner walls")
        return _per_world(env, lambda b, world: self.act_in(world))

    def act_in(self, world) -> dict[str, int]:
        """Actions of one MAgent env's agents by name."""
        north, west, _, south = _unit_moves(world)
        agents, _ = world.positions()
        taken = {tuple(c) for c in agents.tolist()}

        def free(cell: np.ndarray, dx: int, dy: int) -> bool:
            there = (int(cell[0]) + dx, int(cell[1]) + dy)
            return there not in taken and not world.walls[there]

        out = {}
        for name, cell in world.agent_cells().items():
            if free(cell, -1, 0):
                out[name] = west
            elif world.walls[int(cell[0]) - 1, int(cell[1])]:
                out[name] = south if free(cell, 0, 1) else world.stay_action
            else:
                out[name] = north if free(cell, 0, -1) else world.stay_action
        return out


def _per_world(env, act_in) -> np.ndarray:
    """Every slot's action in a MAgent batch from ``act_in(b, world) -> {agent name: action}``;
    slots without an agent (and worlds whose episode is over) stay."""
    actions = np.full((env.batch, env.slots), env.envs[0].stay_action, dtype=np.int64)
    for b, world in enumerate(env.envs):
        if not env.over[b]:
            for name, action in act_in(b, world).items():
                actions[b, world.possible_agents.index(name)] = action  # slot i: agent_i
    return actions


#: The four unit moves of a speed-1 MAgent agent, as ``(dx, dy)``: north, west, east, south.
_STEPS = [(0, -1), (-1, 0), (1, 0), (0, 1)]


def _unit_moves(world) -> list[int]:
    """The action numbers of ``_STEPS`` for the agents of one MAgent env."""
    from udan.envs.magent import move_offsets  # MAgent2 is the [train] extra's

    moves = move_offsets(world.agent_attrs["speed"])
    return [int(np.flatnonzero((moves == d).all(1))[0]) for d in _STEPS]


POLICIES = {
    "random": RandomPolicy,
    "oracle": OraclePolicy,
    "chaser": ChaserPolicy,
    "liner": LinerPolicy,
}
