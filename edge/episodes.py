"""Playing a simulated world's episodes through the edge (``udan-edge --world``, ``--sim``).

Only the HIL world and ``--sim`` have episodes; real cars are simply driven. With a world, the
edge asks it for each episode's layout over its loopback control port, waits until the
episode's cars are in the fleet and the vision has swept the whole new layout once, runs
``steps`` decisions, lets the last moves finish, credits the last step's rewards from one more
frame, and records the returns (the score table the HIL compares with the pure simulation).

The player drives an :class:`udan.edge.shell.EdgeShell` through its public loop (``next_scene``,
``drive``) and its :class:`udan.edge.core.ControlCore`; the shell knows nothing of episodes.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from udan.edge.vision import KEPT_VISITS

if TYPE_CHECKING:
    from udan.edge.shell import EdgeShell


class WorldError(RuntimeError):
    """The HIL world did not answer or refused a request."""


async def world_request(
    address: tuple[str, int], payload: Mapping[str, Any], timeout: float = 5.0
) -> dict[str, Any]:
    """One JSON request/answer with the HIL world's loopback control port."""
    loop = asyncio.get_running_loop()
    answer: asyncio.Future[bytes] = loop.create_future()

    class _Client(asyncio.DatagramProtocol):
        def datagram_received(self, data: bytes, addr: Any) -> None:
            if not answer.done():
                answer.set_result(data)

    transport, _ = await loop.create_datagram_endpoint(_Client, remote_addr=address)
    try:
        transport.sendto(json.dumps(payload).encode())
        data = await asyncio.wait_for(answer, timeout)
    except TimeoutError:
        raise WorldError(f"world at {address[0]}:{address[1]} did not answer {payload}") from None
    finally:
        transport.close()
    reply = json.loads(data)
    if not reply.get("ok", False):
        raise WorldError(f"world refused {payload}: {reply.get('error')}")
    return reply


@dataclass(frozen=True)
class EpisodePlan:
    """Which episodes to play, and how long each may take to start."""

    world: tuple[str, int]
    """The world's control address."""
    episodes: int | None = None
    """How many episodes to play (None: until the world's plan ends)."""
    steps: int = 50
    """Decisions per episode (the arena's episode length)."""
    join_timeout_s: float = 10.0
    """Longest an episode waits for its cars to be in the fleet before it starts."""


class EpisodePlayer:
    """Plays the world's episodes through a shell: ``await EpisodePlayer(plan)(shell)``."""

    def __init__(self, plan: EpisodePlan) -> None:
        self.plan = plan

    async def __call__(self, shell: EdgeShell) -> None:
        """Ask the world for each episode, play it, credit the last step, record the returns."""
        plan, core, index = self.plan, shell.core, 0
        while not shell.stop.is_set() and (plan.episodes is None or index < plan.episodes):
            info = await world_request(plan.world, {"op": "episode", "index": index})
            if info.get("done"):
                break
            laid_out = time.monotonic_ns()
            core.new_episode(laid_out)
            cars = set(info["cars"])
            if not await self._await_fleet(shell, cars, laid_out):
                shell.telemetry.event("episode_skipped", index=index, cars=sorted(cars))
                index += 1
                continue
            slots = {str(c): s for c, s in sorted(core.fleet.slot.items())}
            steps = await shell.drive(plan.steps)
            if steps < plan.steps:  # stopped mid-episode: not a result
                shell.telemetry.event("episode_cut", index=index, steps=steps)
                break
            await self._credit_last_step(shell)
            returns = {str(c): r for c, r in sorted(core.policy_step.returns.items())}
            shell.telemetry.episode(
                {
                    "index": index,
                    **{k: info[k] for k in ("agents", "obstacles", "seed") if k in info},
                    "steps": steps,
                    "returns": returns,
                    "score": sum(returns.values()) / len(returns) if returns else None,
                    "slots": slots,
                    "t_ns": time.monotonic_ns(),
                }
            )
            index += 1

    async def _await_fleet(self, shell: EdgeShell, cars: set[int], laid_out_ns: int) -> bool:
        """Frames until exactly the episode's cars are in the fleet (joined, seen) and the
        vision has read the new layout: ``KEPT_VISITS`` sweeps of the whole image, calibrated,
        in frames captured after the layout changed at ``laid_out_ns``. A marker is placed at
        its tile's next visit, but one taken away leaves the map only after that many visits
        without it (and a tile swept before the camera model was fitted places its markers in
        no cell): after one sweep, the first step of most episodes still saw the last
        episode's obstacles, walls and water, and decided on them (the simulation it is
        compared with did not); the first step of the morning's seed-13 run, before the
        camera was fitted, drove a car into an obstacle it had not placed yet."""
        deadline = time.monotonic() + self.plan.join_timeout_s
        needed, frames = KEPT_VISITS * shell.perception.sweep_frames, 0
        while not shell.stop.is_set() and time.monotonic() < deadline:
            scene = await shell.next_scene()
            frames += scene is not None and scene.calibrated and scene.t_capture_ns >= laid_out_ns
            if set(shell.core.fleet.slot) == cars and frames > needed:
                return True
        return False

    async def _credit_last_step(self, shell: EdgeShell) -> None:
        """Wait for the last moves to end, then credit their rewards from a fresh frame that
        shows every car."""
        core, period_ns = shell.core, int(shell.config.step_timeout_s * 1e9)
        deadline = time.monotonic_ns() + period_ns
        while not shell.stop.is_set() and time.monotonic_ns() < deadline:
            if all(shell.link.move_finished(c) for c in core.fleet.slot):
                break
            await asyncio.sleep(0.002)
        core.not_before_ns = time.monotonic_ns()
        deadline += period_ns
        while not shell.stop.is_set() and time.monotonic_ns() < deadline:
            scene = await shell.next_scene()
            if scene is not None and core.credit_last_step(scene) is not None:
                return
