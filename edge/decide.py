"""One decision step: what the camera saw -> each car's masked view -> one batched policy call
-> the safety filter -> a command per car.

The masking is the training code itself: the static layout comes from the cell markers, and
:func:`udan.envs.arena.scene_codes` + :func:`udan.envs.observe.observe` build each car's
observation exactly as the arena does, with its last action and last reward
(:func:`udan.envs.arena.task_rewards` on the cells the camera sees), so a policy gets the same
numbers on cars as in simulation. Grouping and inference are :class:`export.runtime.OnnxPolicy`
(numpy grouping, one onnxruntime graph), keyed by the fleet's slots.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from edge.geometry import ArenaGeometry
from edge.safety import STOP, Filtered, filter_moves
from export.runtime import OnnxPolicy
from udan.envs.arena import layout_bits, scene_codes, task_rewards
from udan.envs.observe import ObsSpec, observe
from udan.envs.rules import ACTION_DELTAS, OBSTACLE, WAIT, WALL, WATER

_KIND_CODES = {"obstacle": OBSTACLE, "wall": WALL, "water": WATER}
TASKS = ("find_water", "surround")


class TaskError(ValueError):
    """A model whose environment the edge cannot drive cars in."""


def task_of(env: str) -> str:
    """The arena task of a model's ``env`` metadata (``arena/find_water`` -> ``find_water``)."""
    task = env.removeprefix("arena/")
    if not env.startswith("arena/") or task not in TASKS:
        raise TaskError(f"model env {env!r} is not an arena task the cars can play ({TASKS})")
    return task


@dataclass(frozen=True, slots=True)
class Decision:
    """One step's outcome for the cars in ``cars`` (fleet order)."""

    cars: tuple[int, ...]
    actions: np.ndarray  # the policy's greedy actions
    commands: np.ndarray  # after the safety filter (5 = stop)
    rewards: np.ndarray  # reward each car earned by the step that just ended
    blocked: int
    stopped: int
    spans_ns: dict[str, int]


class DecisionStep:
    """Per-episode state of the policy side: last actions and rewards per car, step count."""

    def __init__(
        self, policy: OnnxPolicy, task: str, spec: ObsSpec, geometry: ArenaGeometry | None = None
    ) -> None:
        self.policy = policy
        self.task = task
        self.spec = spec
        self.geometry = geometry or ArenaGeometry(rows=spec.height, cols=spec.width)
        self.reset()

    def reset(self) -> None:
        """A new episode: memories, last actions and rewards, the step counter."""
        self.policy.reset(0)
        self.t = 0
        self.last_action: dict[int, int] = {}
        self.last_reward: dict[int, float] = {}
        self.expected: dict[int, tuple[int, int]] = {}
        self.returns: dict[int, float] = {}
        self._layout_key: tuple[frozenset[tuple[int, int]], ...] | None = None

    def layout(self, cells: Mapping[str, frozenset[tuple[int, int]]]) -> tuple[np.ndarray, ...]:
        """Rules cell codes (H, W) from the static cell markers the camera sees, and their
        padded observation bits; kept while the markers stay (they rarely change)."""
        key = tuple(frozenset(cells.get(kind, ())) for kind in _KIND_CODES)
        if key != self._layout_key:
            grid = np.zeros((self.spec.height, self.spec.width), dtype=np.uint8)
            for kind_cells, code in zip(key, _KIND_CODES.values(), strict=True):
                for row, col in kind_cells:
                    if 0 <= row < self.spec.height and 0 <= col < self.spec.width:
                        grid[row, col] = code
            self._layout_key = key
            self._layout = grid, layout_bits(grid[None], self.spec.view)
        return self._layout

    def decide(
        self,
        slots: Mapping[int, int],
        fresh: set[int],
        cells_of: Mapping[int, tuple[int, int]],
        static: Mapping[str, frozenset[tuple[int, int]]],
        others: list[tuple[int, int]] | None = None,
        moving: Mapping[int, int] | None = None,
    ) -> Decision:
        """Commands for the cars in ``slots`` (car id -> policy slot) standing on ``cells_of``.

        ``fresh``: cars new this step. ``static``: cell markers by kind. ``others``: cells held by
        things the edge does not drive. ``moving``: cars still in a move when the step period
        ran out, with the action they are executing (they get ``wait`` and their destination is
        held for them)."""
        t0 = time.perf_counter_ns()
        cars = tuple(sorted(slots, key=slots.get))
        if not cars:
            return Decision((), *(np.zeros(0, np.int64),) * 2, np.zeros(0, np.float32), 0, 0, {})
        layout, padded = self.layout(static)
        pos, present, target = self._scene(slots, cars, cells_of, static)
        n_slots = pos.shape[1]
        last_action = np.full((1, n_slots), -1, np.int64)
        last_reward = np.zeros((1, n_slots), np.float32)
        idx = np.array([slots[c] for c in cars], np.int64)
        rewards = self._settle(cars, fresh, layout, pos, present, target)
        for car in cars:
            last_action[0, slots[car]] = self.last_action[car]
            last_reward[0, slots[car]] = self.last_reward[car]
        codes = scene_codes(padded, pos, present, self.spec.view, target)
        obs = observe(self.spec, codes, pos, last_action, last_reward, present)[0]
        fresh_mask = np.zeros(n_slots, bool)
        fresh_mask[[slots[c] for c in cars if c in fresh]] = True
        t1 = time.perf_counter_ns()
        actions = self.policy.act(obs, present[0], pos[0], fresh_mask)[idx]
        t2 = time.perf_counter_ns()
        blockers = list(others or []) + sorted(static.get("target", ()))
        filtered = self._filter(layout, cars, pos[0, idx], actions, blockers, moving or {})
        self.t += 1
        t3 = time.perf_counter_ns()
        return Decision(
            cars=cars,
            actions=np.asarray(actions, np.int64),
            commands=filtered.commands,
            rewards=rewards,
            blocked=int(filtered.blocked.sum()),
            stopped=int(filtered.stopped.sum()),
            spans_ns={"masking": t1 - t0, "inference": t2 - t1, "safety": t3 - t2},
        )

    def settle(
        self,
        slots: Mapping[int, int],
        cells_of: Mapping[int, tuple[int, int]],
        static: Mapping[str, frozenset[tuple[int, int]]],
    ) -> np.ndarray:
        """Credit the rewards of the step that just ended without deciding again (the end of an
        episode); returns them in fleet order."""
        cars = tuple(sorted(slots, key=slots.get))
        if not cars or self.t == 0:
            return np.zeros(len(cars), np.float32)
        layout, _ = self.layout(static)
        pos, present, target = self._scene(slots, cars, cells_of, static)
        return self._settle(cars, set(), layout, pos, present, target)

    def _scene(
        self,
        slots: Mapping[int, int],
        cars: tuple[int, ...],
        cells_of: Mapping[int, tuple[int, int]],
        static: Mapping[str, frozenset[tuple[int, int]]],
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Positions (1, S, 2), presence (1, S) and the surround target (1, 2) of one arena."""
        n_slots = max(slots.values()) + 1
        pos = np.zeros((1, n_slots, 2), np.int64)
        present = np.zeros((1, n_slots), bool)
        idx = [slots[c] for c in cars]
        pos[0, idx] = [cells_of[c] for c in cars]
        present[0, idx] = True
        target = None
        if self.task == "surround":
            target_cells = sorted(static.get("target", ()))
            target = np.array([target_cells[0] if target_cells else (-1, -1)], np.int64)
        return pos, present, target

    def _settle(
        self,
        cars: tuple[int, ...],
        fresh: set[int],
        layout: np.ndarray,
        pos: np.ndarray,
        present: np.ndarray,
        target: np.ndarray | None,
    ) -> np.ndarray:
        """Each car's reward for the step that ended (the arena's own reward code), added to its
        return; a new car starts with no last action and no reward."""
        rewards = np.zeros(len(cars), np.float32)
        if self.t > 0:
            step = np.array([self.t])
            all_rewards = task_rewards(self.task, layout[None], pos, present, target, step)[0]
            rewards = all_rewards[np.flatnonzero(present[0])]  # slot order is fleet order
        for i, car in enumerate(cars):
            if car in fresh or car not in self.last_action:
                self.last_action[car] = -1
                self.last_reward[car] = 0.0
                self.expected.pop(car, None)
                rewards[i] = 0.0
            else:
                self.last_reward[car] = float(rewards[i])
                self.returns[car] = self.returns.get(car, 0.0) + float(rewards[i])
        return rewards

    def _filter(
        self,
        layout: np.ndarray,
        cars: tuple[int, ...],
        car_pos: np.ndarray,
        actions: np.ndarray,
        others: list[tuple[int, int]],
        moving: Mapping[int, int],
    ) -> Filtered:
        """The safety filter, then what each car's command should lead to (checked next step)."""
        held = [
            tuple(map(int, car_pos[i] + ACTION_DELTAS[moving[c]]))
            for i, c in enumerate(cars)
            if c in moving
        ]
        blockers = np.array(list(others) + held, np.int64).reshape(-1, 2)
        expected = np.array(
            [(-1, -1) if c in moving else self.expected.get(c, (-1, -1)) for c in cars], np.int64
        )
        wanted = np.where([c in moving for c in cars], WAIT, actions)
        filtered = filter_moves(
            layout, car_pos, wanted, expected=expected.reshape(-1, 2), others=blockers
        )
        for i, car in enumerate(cars):
            self.last_action[car] = int(actions[i])
            command = int(filtered.commands[i])
            if car in moving:
                self.expected[car] = (-1, -1)
            else:
                to = car_pos[i] + ACTION_DELTAS[command if command < STOP else WAIT]
                self.expected[car] = (int(to[0]), int(to[1]))
        for gone in set(self.last_action) - set(cars):
            self.last_action.pop(gone)
            self.expected.pop(gone, None)
        return filtered
