"""Frame -> scene in the edge's loop: perception in threads of the edge against its own process.

A writer process publishes 1920x1200 frames of five moving cars (the HIL renderer, frames drawn
once and replayed) on a virtual camera at 40 FPS, stamped at publication, as the HIL world does.
The edge side is an asyncio loop (uvloop when installed, as in ``udan-edge``) that takes each
frame's scene from a :class:`udan.edge.perception.Perception` and measures capture -> scene in
the loop. The loop does what the edge's does around a frame, in Python: while a frame is being
analysed it rehearses (``REHEARSAL_MS`` of Python, the rehearsal's length in the full loop), and a
timer fires every ``TIMER_MS`` (the dispatcher's resend period), whose lateness shows how long
the loop waited for the interpreter lock or a core. Blocks of ``BLOCK_S`` seconds alternate
thread, process, thread, process, ... on the same frames. The perception process's start-up
(spawned interpreter, imports, camera opened) is timed too. Prints one JSON object.
"""

from __future__ import annotations

import asyncio
import json
import multiprocessing
import os
import sys
import time
import uuid
from typing import Any

import numpy as np

from udan.edge.camera import FrameGrabber, open_camera
from udan.edge.geometry import ArenaGeometry
from udan.edge.perception import (
    FrameTaken,
    Perception,
    ProcessPerception,
    ThreadPerception,
    VisionSettings,
)
from udan.hil.render import Renderer, circling_cars
from udan.hil.vcam import VirtualCamera

TARGET_P99_MS = 5.0  # the vision's budget: the scene should reach the loop within it
BLOCKS = int(os.environ.get("BENCH_BLOCKS", "6"))
BLOCK_S = float(os.environ.get("BENCH_BLOCK_S", "10"))
WARM_UP_FRAMES = 30  # two sweeps: cars found, tracks running
REHEARSAL_MS = 0.6
TIMER_MS = 2.0
CARS = 5
CYCLE = 80  # frames drawn once, then replayed (2 s of motion, closing on itself)


def _publish(name: str, ready, stop) -> None:
    """The writer process: draw the cycle, then publish it at 40 FPS until told to stop."""
    frames = circling_cars(Renderer(ArenaGeometry()), CYCLE, CARS)
    with VirtualCamera(name, fps=40.0) as cam:
        ready.set()
        cam.run(lambda _t, out: np.copyto(out, frames[cam.frames % CYCLE]), stop=stop)


def _percentiles(ms: list[float]) -> dict[str, float | int]:
    a = np.asarray(ms)
    return {
        "n": int(a.size),
        "p50": round(float(np.median(a)), 3),
        "p99": round(float(np.percentile(a, 99)), 3),
        "max": round(float(a.max()), 3),
    }


def _busy(ms: float) -> None:
    """Python work for ``ms`` milliseconds (holds the interpreter lock, as a rehearsal does)."""
    end = time.perf_counter_ns() + int(ms * 1e6)
    x = 0
    while time.perf_counter_ns() < end:
        x += sum(range(50))


async def _timer(late_ms: list[float], stop: asyncio.Event) -> None:
    """How late a timer fires (measured on time.monotonic: uvloop's loop.time() counts whole
    milliseconds)."""
    period = TIMER_MS / 1e3
    due = time.monotonic() + period
    while not stop.is_set():
        await asyncio.sleep(max(0.0, due - time.monotonic()))
        late_ms.append(max(0.0, time.monotonic() - due) * 1e3)
        due = max(due + period, time.monotonic())


async def _block(perception: Perception) -> dict[str, Any]:
    """One block: frame -> scene in this loop, and the timer's lateness meanwhile."""
    perception.start()
    latency_ms: list[float] = []
    late_ms: list[float] = []
    stop = asyncio.Event()
    timer = asyncio.ensure_future(_timer(late_ms, stop))
    seen = 0
    end = time.monotonic() + BLOCK_S
    try:
        while time.monotonic() < end:
            event = await perception.next_event(timeout=1.0)
            if isinstance(event, FrameTaken):
                _busy(REHEARSAL_MS)
            elif event is not None:
                seen += 1
                if seen > WARM_UP_FRAMES:
                    latency_ms.append((time.monotonic_ns() - event.t_capture_ns) / 1e6)
    finally:
        stop.set()
        await timer
        perception.close()
    return {"latency": latency_ms, "late": late_ms, "dropped": perception.dropped}


async def _measure(camera: str) -> dict[str, object]:
    settings = VisionSettings(ArenaGeometry(), tuple(range(5, 5 + CARS)))
    samples: dict[str, dict[str, list]] = {
        kind: {"latency": [], "late": [], "dropped": []} for kind in ("thread", "process")
    }
    start_up_s = []
    for block in range(BLOCKS):
        kind = ("thread", "process")[block % 2]
        if kind == "process":
            t0 = time.perf_counter()
            perception: Perception = ProcessPerception(camera, settings)
            perception.wait_ready()
            start_up_s.append(time.perf_counter() - t0)
        else:
            perception = ThreadPerception(FrameGrabber(open_camera(camera)), settings.build())
        got = await _block(perception)
        samples[kind]["latency"] += got["latency"]
        samples[kind]["late"] += got["late"]
        samples[kind]["dropped"].append(got["dropped"])
    result: dict[str, object] = {}
    for kind, s in samples.items():
        result[kind] = {
            "frame_to_scene_ms": _percentiles(s["latency"]),
            "timer_late_ms": _percentiles(s["late"]),
            "dropped_per_block": s["dropped"],
        }
    result["process_start_up_s"] = _percentiles(start_up_s)
    return result


def _runner():
    try:
        import uvloop
    except ImportError:
        return asyncio.run
    return uvloop.run


def main() -> int:
    name = f"udan-bench-{uuid.uuid4().hex[:8]}"
    context = multiprocessing.get_context("spawn")
    ready, stop = context.Event(), context.Event()
    writer = context.Process(target=_publish, args=(name, ready, stop), daemon=True)
    writer.start()
    try:
        if not ready.wait(120):
            raise SystemExit("bench/perception.py: the frame writer did not start")
        measured = _runner()(_measure(f"virtual://{name}"))
    finally:
        stop.set()
        writer.join(10)
    thread_p99 = measured["thread"]["frame_to_scene_ms"]["p99"]
    process_p99 = measured["process"]["frame_to_scene_ms"]["p99"]
    result = {
        "benchmark": "perception",
        "frame": [1920, 1200],
        "cars": CARS,
        "fps": 40,
        "blocks": BLOCKS,
        "block_s": BLOCK_S,
        "loop_load": {"rehearsal_ms_per_frame": REHEARSAL_MS, "timer_period_ms": TIMER_MS},
        "load_average_1m": round(os.getloadavg()[0], 2),
        **measured,
        "process_to_thread_p99": round(process_p99 / thread_p99, 3),
        "target_p99_ms": TARGET_P99_MS,
        "meets_target": process_p99 <= TARGET_P99_MS,
    }
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
