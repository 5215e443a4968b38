"""One decision step: what the camera saw -> each car's masked view -> one batched policy call
-> the safety filter -> a command per car.

The masking is the training code itself: the static layout comes from the cell markers, and
:func:`udan.envs.arena.scene_codes` + :func:`udan.envs.observe.observe` build each car's
observation exactly as the arena does, with its last action and last reward
(:func:`udan.envs.arena.task_rewards` on the cells the camera sees), so a policy gets the same
numbers on cars as in simulation. Grouping and inference are :class:`udan.export.runtime.OnnxPolicy`
(grouping from :mod:`udan.envs.grouping`, one onnxruntime graph), keyed by the fleet's slots.
The observations are written straight into the graph's bound input buffer.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from udan import _kernels
from udan.edge.fleet import FleetState
from udan.edge.protocol import Guidance
from udan.edge.safety import Filtered, filter_moves
from udan.envs.arena import layout_bits, scene_codes, task_rewards
from udan.envs.observe import ObsSpec, observe
from udan.envs.rules import ACTION_DELTAS, OBSTACLE, WAIT, WALL, WATER

if TYPE_CHECKING:  # the caller builds the policy; deciding needs only its methods
    from udan.export.runtime import OnnxPolicy

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
    formed: bool = False  # the policy formed groups this step (its slowest kind of step)
    targets: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    """(N, 2) the cell each car's command takes it to (a car still in a move: the cell its
    move is heading for)."""
    guidance: Mapping[int, Guidance] = field(default_factory=dict)
    """Per car: its target cell's centre and its measured pose, for the command (filled by
    the control core, which knows where the cells are and where the camera saw the cars)."""
    after: Mapping[int, int] = field(default_factory=dict)
    """Car -> the car whose cell it enters as that one leaves: its command goes out only once
    that car accepted its own (filled by the control core)."""


def _blockers(
    static: Mapping[str, frozenset[tuple[int, int]]], others: list[tuple[int, int]] | None = None
) -> list[tuple[int, int]]:
    """Cells the safety filter keeps the cars out of: things the edge does not drive
    (``others``) and the surround target."""
    return list(others or []) + sorted(static.get("target", ()))


class DecisionStep:
    """The policy side of one arena: per-slot last action, last reward, where each car should
    be after its command, and its return this episode. State lives in arrays indexed by the
    fleet's policy slot (a slot keeps its car until the car leaves), so a step costs a few
    numpy calls whether 5 or 1,000 cars are driven."""

    def __init__(self, policy: OnnxPolicy, task: str, spec: ObsSpec) -> None:
        self.policy = policy
        self.task = task
        self.spec = spec
        self.owner = np.zeros(0, np.int64)
        self._fleet_key: dict[int, int] | None = None  # the slots _fleet_arrays are for
        self._fleet_arrays: tuple[np.ndarray, ...] | None = None
        self._cars: tuple[int, ...] = ()  # the car ids of _fleet_arrays, for each Decision
        self.reset()

    def reset(self) -> None:
        """A new episode: memories, last actions and rewards, returns, the step counter. The
        slots stay (empty), so the policy keeps its bindings and the fleet's arrays
        (:meth:`_fleet`) stay valid for the same fleet."""
        slots = len(self.owner)
        self.policy.reset(slots)
        self.t = 0
        self.owner = np.full(slots, -1, np.int64)  # car id per slot, -1 for none
        self.last_action = np.full(slots, -1, np.int64)
        self.last_reward = np.zeros(slots, np.float32)
        self.expected = np.full((slots, 2), -1, np.int64)  # -1: no expectation
        self.slot_return = np.zeros(slots, np.float64)
        self._banked: dict[int, float] = {}
        self._layout_key: tuple[frozenset[tuple[int, int]], ...] | None = None
        self._last: tuple | None = None  # the last step's inputs, for rehearse
        self._owned_key: dict[int, int] | None = None  # _fleet_key last credited: cars own them

    @property
    def returns(self) -> dict[int, float]:
        """Each car's return this episode (cars that left keep what they earned)."""
        out = dict(self._banked)
        for slot in np.flatnonzero(self.owner >= 0):
            car = int(self.owner[slot])
            out[car] = out.get(car, 0.0) + float(self.slot_return[slot])
        return out

    def groups(self) -> list[list[int]]:
        """The policy's groups as they stand after the last step, as car ids, leader first then
        by distance (a car in several groups bridges them); empty for a policy without them."""
        groups = self.policy.groups
        if groups.size == 0:
            return []
        return self.owner[groups].tolist()

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

    def decide(self, state: FleetState) -> Decision:
        """Commands for the cars of ``state`` (the fleet as this step sees it): cars in
        ``state.moving`` get ``wait`` and their destination is held for them."""
        t0 = time.perf_counter_ns()
        slots, fresh, cells_of, static = state.slots, state.fresh, state.cells, state.static
        if not slots:
            return Decision((), *(np.zeros(0, np.int64),) * 2, np.zeros(0, np.float32), 0, 0, {})
        layout, padded = self.layout(static)
        cars, idx, pos, present, target = self._scene(slots, cells_of, static)
        # the slots last credited, kept since (no fresh car): every car owns its slot already
        steady = not fresh and self._owned_key is self._fleet_key
        fresh_mask = np.zeros(len(self.owner), bool)
        if fresh:
            fresh_mask[[slots[c] for c in fresh if c in slots]] = True
        rewards = self._credit(cars, idx, fresh_mask, layout, pos, present, target, steady)
        obs = self._observe(padded, pos, present, target, self.policy.observations(len(self.owner)))
        t1 = time.perf_counter_ns()
        actions = self.policy.act(obs, present[0], pos[0], fresh_mask)[idx]
        t2 = time.perf_counter_ns()
        blockers = _blockers(static, state.others)
        filtered, targets = self._filter(
            layout, cars, idx, pos[0, idx], actions, blockers, state.moving
        )
        self.t += 1
        self._last = layout, padded, pos, present, idx, target, blockers
        t3 = time.perf_counter_ns()
        return Decision(
            cars=self._cars,
            actions=actions,
            commands=filtered.commands,
            rewards=rewards,
            blocked=int(np.count_nonzero(filtered.blocked)),
            stopped=int(np.count_nonzero(filtered.stopped)),
            spans_ns={"masking": t1 - t0, "inference": t2 - t1, "safety": t3 - t2},
            formed=self.policy.formed,
            targets=targets,
        )

    def rehearse(
        self,
        slots: Mapping[int, int] | None = None,
        cells_of: Mapping[int, tuple[int, int]] | None = None,
        static: Mapping[str, frozenset[tuple[int, int]]] | None = None,
    ) -> bool:
        """The last step's masking, policy work and safety filter once more, keeping nothing a
        decision reads (:meth:`udan.export.runtime.OnnxPolicy.rehearse`); given ``slots``,
        ``cells_of`` and ``static``, those instead: the step a new episode's fleet would make
        from where it stands. The runtime calls it while the frame it will decide on is being
        analysed: a decision after ~50 ms of idling or of OpenCV work takes ~3x as long as one
        right after another (the caches have gone cold; measured in docs/timing.md), and this
        warms them. False, having done nothing, when there is nothing to rehearse: no last step
        (a new episode) and none given, or a fleet in more slots than the step has (its
        decision grows the per-slot state and binds the policy anew, which a rehearsal must
        not do)."""
        if slots is not None and cells_of is not None and static is not None:
            if not slots or max(slots.values()) >= len(self.owner):
                return False
            layout, padded = self.layout(static)
            _, idx, pos, present, target = self._scene(slots, cells_of, static)
            blockers = _blockers(static)
        elif self._last is not None:
            layout, padded, pos, present, idx, target, blockers = self._last
        else:
            return False
        task_rewards(self.task, layout[None], pos, present, target, np.array([self.t]))
        obs = self._observe(padded, pos, present, target, self.policy.observations(len(self.owner)))
        if not self.policy.rehearse(obs, present[0], pos[0]):
            return False
        filter_moves(layout, pos[0, idx], self.last_action[idx], others=blockers)
        return True

    def credit_last_step(
        self,
        slots: Mapping[int, int],
        cells_of: Mapping[int, tuple[int, int]],
        static: Mapping[str, frozenset[tuple[int, int]]],
    ) -> np.ndarray:
        """Credit the rewards of the step that just ended without deciding again (the end of an
        episode); returns them in fleet order."""
        if not slots or self.t == 0:
            return np.zeros(len(slots), np.float32)
        layout, _ = self.layout(static)
        cars, idx, pos, present, target = self._scene(slots, cells_of, static)
        return self._credit(
            cars, idx, np.zeros(len(self.owner), bool), layout, pos, present, target
        )

    def _scene(
        self,
        slots: Mapping[int, int],
        cells_of: Mapping[int, tuple[int, int]],
        static: Mapping[str, frozenset[tuple[int, int]]],
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """Car ids in slot order, their slots, positions (1, S, 2), presence (1, S), surround
        target (1, 2); the per-slot state grows to S slots. The cells are read from the mapping
        in one loop in C (a Python loop per car costs ~1 ms at 1,000 cars)."""
        cars, idx, present = self._fleet(slots)
        pos = np.zeros((1, len(self.owner), 2), np.int64)
        _kernels.gather_cells(cells_of, self._cars, idx, pos[0])
        target = None
        if self.task == "surround":
            target_cells = sorted(static.get("target", ()))
            target = np.array([target_cells[0] if target_cells else (-1, -1)], np.int64)
        return cars, idx, pos, present, target

    def _fleet(self, slots: Mapping[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Car ids in slot order, their slots, and presence (1, S), all read-only: kept while
        the fleet keeps its slots, which is most steps (building them is ~8 numpy calls)."""
        if slots == self._fleet_key:
            return self._fleet_arrays
        n = len(slots)
        car_ids = np.fromiter(slots.keys(), np.int64, n)
        slot_of = np.fromiter(slots.values(), np.int64, n)
        order = np.argsort(slot_of, kind="stable")
        cars, idx = car_ids[order], slot_of[order]
        n_slots = int(idx[-1]) + 1
        if n_slots > len(self.owner):
            grow = n_slots - len(self.owner)
            self.owner = np.concatenate([self.owner, np.full(grow, -1, np.int64)])
            self.last_action = np.concatenate([self.last_action, np.full(grow, -1, np.int64)])
            self.last_reward = np.concatenate([self.last_reward, np.zeros(grow, np.float32)])
            self.expected = np.concatenate([self.expected, np.full((grow, 2), -1, np.int64)])
            self.slot_return = np.concatenate([self.slot_return, np.zeros(grow)])
        present = np.zeros((1, len(self.owner)), bool)
        present[0, idx] = True
        for array in (cars, idx, present):
            array.flags.writeable = False
        self._fleet_key, self._fleet_arrays = dict(slots), (cars, idx, present)
        self._cars = tuple(cars.tolist())
        return self._fleet_arrays

    def _observe(
        self,
        padded: np.ndarray,
        pos: np.ndarray,
        present: np.ndarray,
        target: np.ndarray | None,
        out: np.ndarray,
    ) -> np.ndarray:
        """Every slot's observation (S, D) of the scene, with its last action and reward,
        written into ``out`` (the policy's bound buffer: the graph reads it from there)."""
        codes = scene_codes(padded, pos, present, self.spec.view, target)
        last_action, last_reward = self.last_action[None], self.last_reward[None]
        return observe(self.spec, codes, pos, last_action, last_reward, present, out[None])[0]

    def _credit(
        self,
        cars: np.ndarray,
        idx: np.ndarray,
        fresh: np.ndarray,
        layout: np.ndarray,
        pos: np.ndarray,
        present: np.ndarray,
        target: np.ndarray | None,
        steady: bool = False,
    ) -> np.ndarray:
        """Each car's reward for the step that ended (the arena's own reward code), added to its
        return; a car new to its slot, or ``fresh`` (per slot), starts with no last action, no
        reward, no return, and its slot is marked in ``fresh`` (in place) so the policy starts
        its memory empty too, flagged by the caller or not. ``steady``: the slots are those
        last credited and no car is fresh, so every car already owns its slot."""
        arrived = False
        if not steady:
            new = (self.owner[idx] != cars) | fresh[idx]
            arrived = new.any()  # rare once the fleet is steady
        if arrived:
            for slot in idx[new & (self.owner[idx] >= 0)]:
                old = int(self.owner[slot])
                self._banked[old] = self._banked.get(old, 0.0) + float(self.slot_return[slot])
            self.owner[idx] = cars
            renew = idx[new]
            fresh[renew] = True
            self.last_action[renew] = -1
            self.last_reward[renew] = 0.0
            self.expected[renew] = -1
            self.slot_return[renew] = 0.0
        self._owned_key = self._fleet_key  # the slots _scene built cars and idx from
        rewards = np.zeros(len(cars), np.float32)
        if self.t > 0:
            step = np.array([self.t])
            rewards = task_rewards(self.task, layout[None], pos, present, target, step)[0][idx]
            if arrived:
                rewards[new] = 0.0
            self.last_reward[idx] = rewards
            self.slot_return[idx] += rewards
        return rewards

    def _filter(
        self,
        layout: np.ndarray,
        cars: np.ndarray,
        idx: np.ndarray,
        car_pos: np.ndarray,
        actions: np.ndarray,
        others: list[tuple[int, int]],
        moving: Mapping[int, int] | None,
    ) -> tuple[Filtered, np.ndarray]:
        """The safety filter, then where each car's command should take it (checked next step),
        and the cell each car's command aims at. Cars still in a move are not checked and hold
        the cell they are heading for."""
        expected, wanted, in_move = self.expected[idx], actions, None
        targets = None
        if moving:
            in_move = np.fromiter((c in moving for c in cars.tolist()), bool, len(cars))
            doing = np.fromiter((moving[c] for c in cars[in_move].tolist()), np.int64)
            doing[doing > WAIT] = WAIT  # halted by the guard's stop: it holds where it stands
            heading_for = car_pos[in_move] + ACTION_DELTAS[doing]
            others = others + heading_for.tolist()
            expected = np.where(in_move[:, None], -1, expected)
            wanted = np.where(in_move, WAIT, actions)
        filtered = filter_moves(layout, car_pos, wanted, expected=expected, others=others)
        self.last_action[idx] = actions
        step_to = filtered.dest
        if in_move is not None:
            step_to = np.where(in_move[:, None], -1, step_to)
            targets = filtered.dest.copy()
            targets[in_move] = heading_for
        self.expected[idx] = step_to
        return filtered, filtered.dest if targets is None else targets

    def expected_cell(self, slot: int) -> tuple[int, int] | None:
        """Where the last command sent the car in ``slot`` (None: nowhere in particular)."""
        if slot >= len(self.expected) or self.expected[slot, 0] < 0:
            return None
        row, col = self.expected[slot].tolist()
        return row, col

    def redirect(self, slot: int, cell: tuple[int, int]) -> None:
        """The edge sent the car in ``slot`` to ``cell`` outside a step (re-centring): it is
        expected there, not stopped for being there (before its first step a car is expected
        nowhere: nothing to change)."""
        if slot < len(self.expected):
            self.expected[slot] = cell
