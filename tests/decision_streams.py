"""Recorded decision streams: what the edge's decision step was given, step after step, and what
it decided, made by the code of a pinned commit (the previous implementation) for the policy
committed now. ``tests/test_decision_streams.py`` feeds the same inputs to today's
:class:`udan.edge.decide.DecisionStep` and wants the same decisions, bit for bit.

Regenerate (whenever the committed policy changes, or a change is meant to change decisions:
then move ``PREVIOUS`` to that change's commit and say so)::

    .venv/bin/python tests/decision_streams.py            # code of PREVIOUS, models/find_water
    .venv/bin/python tests/decision_streams.py --code REV --model PATH -o FILE

The recording runs in a child interpreter that imports ``udan.*`` from a copy of the pinned
commit's tree (``git archive``), so what is recorded is the old code's behaviour, whatever the
checkout holds. Each scenario is an arena episode stepped with the decided commands: fleets
of 1 to 1,000 cars, cars joining and leaving mid-episode (churn: fresh cars, reused slots),
groups bridged by shared members, cars seen off the cell they were sent to, cars still in a
move (or halted in one by the guard), markers of things the edge does not drive, and
rehearsals between steps.
"""

from __future__ import annotations

import argparse
import gzip
import hashlib
import json
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "tests" / "data" / "decision_streams.json.gz"
DEFAULT_MODEL = ROOT / "models" / "find_water" / "policy.onnx"
#: The implementation the streams are recorded with: main's decision step before issue 25's
#: loops in C (with the moving cars' targets and the guard's stops of issue 29).
PREVIOUS = "23399b055f7723eb2990ce6a406a240df8de120d"
#: What the recording imports, by path in the source tree -> path in the ``udan`` namespace.
PACKAGES = {
    "udan": "udan",
    "edge": "udan/edge",
    "export": "udan/export",
    "models/__init__.py": "udan/models/__init__.py",
}


@dataclass(frozen=True)
class Scenario:
    """One recorded stream: an arena, how many episodes and steps, and how rough the camera
    and the cars are."""

    name: str
    task: str
    agents: tuple[int, int]
    obstacles: tuple[int, int]
    size: int
    episodes: int
    steps: int
    churn: float
    seed: int
    rough: float = 0.1
    """Per step: the chance of each kind of trouble (a car seen off its cell, a car still in
    a move, a marker that is not a car of the fleet, a rehearsal before the step)."""


SCENARIOS = (
    Scenario("find_water 1-5", "find_water", (1, 5), (0, 9), 9, 4, 50, 0.15, 0),
    Scenario("surround 2-8", "surround", (2, 8), (0, 6), 9, 3, 50, 0.2, 1),
    Scenario("surround 20-28", "surround", (20, 28), (10, 30), 20, 2, 40, 0.6, 2),
    Scenario("surround 60-68", "surround", (60, 68), (20, 60), 30, 2, 30, 0.6, 3),
    Scenario("surround 180-260", "surround", (180, 260), (50, 100), 50, 1, 25, 0.5, 4),
    Scenario("surround 950-1000", "surround", (950, 1000), (150, 200), 100, 1, 25, 0.5, 5),
)


def digest(array) -> str:
    """sha256 of an array's bytes (C order)."""
    import numpy as np

    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()


def _outputs(step, decision) -> dict:
    """What a decision is compared on: everything the step hands on, the policy's inputs
    (observations, groups) and its actions."""
    policy = step.policy
    return {
        "cars": list(decision.cars),
        "actions": decision.actions.tolist(),
        "commands": decision.commands.tolist(),
        "rewards": decision.rewards.tolist(),
        "blocked": decision.blocked,
        "stopped": decision.stopped,
        "formed": decision.formed,
        "targets": decision.targets.tolist(),
        "groups": policy.groups.tolist() if decision.formed else None,
        "obs": digest(policy._steps.obs),
    }


def _free_cell(rng, world, taken: set, near=None):
    """A passable cell nobody is on (next to ``near`` if given), or None."""
    from udan.envs.rules import ACTION_DELTAS, FREE

    height, width = world.layout.shape[1:]
    if near is None:
        candidates = [(int(r), int(c)) for r, c in rng.integers(0, [height, width], (8, 2))]
    else:
        candidates = [(near[0] + int(dr), near[1] + int(dc)) for dr, dc in ACTION_DELTAS[:4]]
        rng.shuffle(candidates)
    for row, col in candidates:
        inside = 0 <= row < height and 0 <= col < width
        if inside and world.layout[0, row, col] == FREE and (row, col) not in taken:
            return row, col
    return None


def record(scenario: Scenario, model: Path) -> list[dict]:
    """The events of one scenario, decided by whatever ``udan`` this interpreter imports."""
    import numpy as np

    from udan.edge.decide import DecisionStep
    from udan.edge.fleet import FleetState
    from udan.edge.safety import STOP
    from udan.envs.arena import ArenaBatch, ArenaConfig
    from udan.envs.rules import OBSTACLE, WALL, WATER
    from udan.export.runtime import OnnxPolicy

    kinds = {"obstacle": OBSTACLE, "wall": WALL, "water": WATER}
    cfg = ArenaConfig(
        task=scenario.task,
        agents=scenario.agents,
        obstacles=scenario.obstacles,
        height=scenario.size,
        width=scenario.size,
        churn=scenario.churn,
    )
    world = ArenaBatch(cfg, 1, seed=scenario.seed)
    step = DecisionStep(OnnxPolicy(model), cfg.task, cfg.spec)
    rng = np.random.default_rng(scenario.seed + 1000)
    rough = scenario.rough
    events: list[dict] = []
    for episode in range(scenario.episodes):
        world.reset()
        if episode:
            step.reset()
            events.append({"reset": True})
        static = {
            kind: sorted(map(tuple, np.argwhere(world.layout[0] == code).tolist()))
            for kind, code in kinds.items()
        }
        last_cars: set[int] = set()
        moves: dict[int, int] = {}  # car -> the move it was last sent (0-3)
        for t in range(scenario.steps):
            if cfg.task == "surround":
                static["target"] = [tuple(world.target[0].tolist())]
            present = np.flatnonzero(world.present[0])
            slots = {int(world.agent_id[0, s]) + 1: int(s) for s in present}
            cells = {car: tuple(world.pos[0, s].tolist()) for car, s in slots.items()}
            taken = set(cells.values()) | set(static.get("target", []))
            for car in list(cells):
                if rng.random() < rough / 3:  # pushed, slipped: seen next to its cell
                    off = _free_cell(rng, world, taken, near=cells[car])
                    if off is not None:
                        taken.add(off)
                        cells[car] = off
            others = []
            if rng.random() < rough:
                cell = _free_cell(rng, world, taken)
                if cell is not None:
                    others.append(cell)
            moving = {}
            if rng.random() < rough:  # the step period ran out: some cars still move
                movers = sorted(set(moves) & set(slots))
                for car in movers[: max(1, len(movers) // 8)]:  # some halted by the guard
                    moving[car] = STOP if rng.random() < 0.25 else moves[car]
            event = {
                "slots": [[car, slot] for car, slot in slots.items()],
                "fresh": sorted(set(slots) - last_cars),
                "cells": [[car, *cell] for car, cell in cells.items()],
                "static": {kind: [list(c) for c in cs] for kind, cs in static.items()},
                "others": [list(c) for c in others],
                "moving": [[car, action] for car, action in moving.items()],
            }
            if rng.random() < rough:
                event["rehearse"] = "given" if t == 0 else "last"
                event["rehearsed"] = _rehearse(step, event)
            decision = step.decide(_state(FleetState, event))
            event["out"] = _outputs(step, decision)
            events.append(event)
            commands = np.full(world.slots, 4)
            commands[list(slots.values())] = np.minimum(decision.commands, 4)
            moves = {
                car: command
                for car, command in zip(decision.cars, decision.commands.tolist(), strict=True)
                if command < 4
            }
            last_cars = set(slots)
            world.step(commands[None])
        slots = {int(world.agent_id[0, s]) + 1: int(s) for s in np.flatnonzero(world.present[0])}
        event = {
            "credit": True,
            "slots": [[car, slot] for car, slot in slots.items()],
            "cells": [[car, *world.pos[0, s].tolist()] for car, s in slots.items()],
            "static": {kind: [list(c) for c in cs] for kind, cs in static.items()},
        }
        event["out"] = _credit(step, event)
        events.append(event)
    return events


def _state(fleet_state, event: dict):
    """The ``FleetState`` of a recorded step."""
    return fleet_state(
        slots={car: slot for car, slot in event["slots"]},
        fresh=set(event["fresh"]),
        cells={car: (row, col) for car, row, col in event["cells"]},
        static={kind: frozenset(map(tuple, cs)) for kind, cs in event["static"].items()},
        others=[tuple(c) for c in event["others"]],
        moving={car: action for car, action in event["moving"]},
    )


def _rehearse(step, event: dict) -> bool:
    """The rehearsal a recorded step asks for before it is decided."""
    if event["rehearse"] == "last":
        return step.rehearse()
    state = _state(lambda **fields: fields, event)
    return step.rehearse(state["slots"], state["cells"], state["static"])


def _credit(step, event: dict) -> dict:
    """The end of an episode: the last step's rewards, and every car's return."""
    state = _state(lambda **fields: fields, {**event, "fresh": [], "others": [], "moving": []})
    rewards = step.credit_last_step(state["slots"], state["cells"], state["static"])
    return {
        "rewards": rewards.tolist(),
        "returns": sorted([car, value] for car, value in step.returns.items()),
    }


def replay(step, events: list[dict]) -> list[dict]:
    """Each recorded event again on the decision step ``step``: :func:`record`'s events with
    today's outputs (and rehearsals' answers)."""
    from udan.edge.fleet import FleetState

    out = []
    for event in events:
        event = dict(event)
        if event.get("reset"):
            step.reset()
        elif event.get("credit"):
            event["out"] = _credit(step, event)
        else:
            if "rehearse" in event:
                event["rehearsed"] = _rehearse(step, event)
            event["out"] = _outputs(step, step.decide(_state(FleetState, event)))
        out.append(event)
    return out


def _child(tree: Path, model: Path, out: Path) -> None:
    """Record every scenario with the ``udan`` of ``tree`` (this runs in the child)."""
    sys.path.insert(0, str(tree))
    import udan.edge.decide

    if not Path(udan.edge.decide.__file__).resolve().is_relative_to(tree.resolve()):
        sys.exit(f"decision_streams: udan.edge came from {udan.edge.decide.__file__}, not {tree}")
    streams = {
        "model_sha256": hashlib.sha256(model.read_bytes()).hexdigest(),
        "scenarios": {s.name: record(s, model) for s in SCENARIOS},
    }
    out.write_text(json.dumps(streams))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--code", default=PREVIOUS, help="commit whose decision step records")
    parser.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="ONNX policy")
    parser.add_argument("-o", "--out", type=Path, default=DEFAULT_OUT, help="streams file")
    parser.add_argument("--tree", type=Path, help=argparse.SUPPRESS)  # the child's source tree
    parser.add_argument("--raw", type=Path, help=argparse.SUPPRESS)  # the child's output
    args = parser.parse_args(argv)
    if args.tree is not None:
        _child(args.tree, args.model.resolve(), args.raw)
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        src, tree = Path(tmp) / "src", Path(tmp) / "tree"
        src.mkdir()
        archive = subprocess.run(
            ["git", "-C", str(ROOT), "archive", args.code, *PACKAGES],
            check=True,
            capture_output=True,
        ).stdout
        subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
        for folder, package in PACKAGES.items():
            (tree / package).parent.mkdir(parents=True, exist_ok=True)
            (src / folder).rename(tree / package)
        raw = Path(tmp) / "streams.json"
        command = [sys.executable, "-P", __file__, "--tree", str(tree), "--raw", str(raw)]
        subprocess.run([*command, "--model", str(args.model.resolve())], check=True, cwd=tmp)
        streams = json.loads(raw.read_text())
    code = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", args.code], check=True, capture_output=True, text=True
    ).stdout.strip()
    streams["code"] = code
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(args.out, "wt") as f:
        json.dump(streams, f, separators=(",", ":"))
    steps = sum(len(events) for events in streams["scenarios"].values())
    print(f"decision_streams: {steps} events of {code[:9]} for {args.model} -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
