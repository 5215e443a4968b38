"""Decision latency with the live page and 10 clients attached, against without it.

Blocks of ``BENCH_BLOCK_S`` seconds alternate A, B, A, B, ... (``BENCH_BLOCKS`` pairs), each a
fresh ``udan-edge --sim --cars 5`` run: A without ``--web``; B with ``--web 127.0.0.1:0`` and
``CLIENTS`` WebSocket clients connected for the whole block, each counting the page states it
receives (it must get them at 9 Hz or more, or the page was not really attached). The decision
latency is each step's ``state_to_commands`` from the run's telemetry, taken after the first
``WARM_UP_S`` of a block (start-up, first episode; by then B's clients are connected). The ratio
is p99(B) / p99(A) over every step of each arm, with a 95 % CI from resampling the pairs of
blocks; deadline misses are the runs' own counts. ``BENCH_REALTIME=1`` runs the edge with
``--realtime`` (needs CAP_SYS_NICE). Prints one JSON object with its targets and verdicts.

    .venv/bin/python -P bench/web.py > out/bench/web.json
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import sys
import tempfile
import time
from pathlib import Path

import aiohttp
import numpy as np

from udan.edge.live import PERIOD_NS
from udan.hil.ab import Block, p99_ms, p99_ratio, read_block, sim_command

BLOCKS = int(os.environ.get("BENCH_BLOCKS", "5"))
BLOCK_S = float(os.environ.get("BENCH_BLOCK_S", "60"))
REALTIME = os.environ.get("BENCH_REALTIME") == "1"
CLIENTS = 10
WARM_UP_S = 10.0
TARGET_RATIO = 1.05
TARGET_UPDATE_HZ = 0.9 * 1e9 / PERIOD_NS  # 9 Hz: nine in ten of the updates the edge offers
URL_LINE = re.compile(rb"^udan-edge: live view at (http://\S+/)")
STATE = '{"kind": "state"'  # how the page's state messages begin


async def _client(url: str, until: float) -> dict[str, float]:
    """One page's worth of WebSocket: states received and over how long."""
    states, first, last = 0, None, None
    try:
        async with aiohttp.ClientSession() as session, session.ws_connect(url + "ws") as ws:
            while (left := until - time.monotonic()) > 0:
                try:
                    message = await ws.receive(timeout=left)
                except TimeoutError:
                    break
                if message.type == aiohttp.WSMsgType.TEXT and message.data.startswith(STATE):
                    now = time.monotonic()
                    first = now if first is None else first
                    last, states = now, states + 1
                elif message.type in (aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR):
                    break
    except aiohttp.ClientError:
        pass
    span = (last - first) if first is not None and last is not None else 0.0
    return {"states": states, "hz": round((states - 1) / span, 2) if span > 0 else 0.0}


async def _block(web: bool, folder: Path) -> tuple[Block, list[float]]:
    """One run of the edge (:mod:`udan.hil.ab`'s block), and its clients' update rates."""
    cmd = sim_command(["--web", "127.0.0.1:0"] if web else [], folder, BLOCK_S, REALTIME)
    proc = await asyncio.create_subprocess_exec(
        *cmd, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )
    started_ns = time.monotonic_ns()
    clients: list[dict[str, float]] = []
    if web:
        assert proc.stdout is not None
        match = URL_LINE.match(await proc.stdout.readline())
        if match is None:
            raise SystemExit(f"bench/web.py: no live view: {(await proc.stderr.read())[-500:]}")
        until = time.monotonic() + BLOCK_S
        clients = list(
            await asyncio.gather(*(_client(match.group(1).decode(), until) for _ in range(CLIENTS)))
        )
    _, err = await proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"bench/web.py: udan-edge exited {proc.returncode}: {err[-500:]!r}")
    return read_block(folder, started_ns, WARM_UP_S), [c["hz"] for c in clients]


async def _measure(folder: Path) -> tuple[list[Block], list[Block], list[float]]:
    plain, web, rates = [], [], []
    for i in range(BLOCKS):
        for arm, runs in (("plain", plain), ("web", web)):
            block = folder / f"{arm}{i}"
            block.mkdir()
            run, hz = await _block(arm == "web", block)
            runs.append(run)
            rates += hz
            print(f"bench/web.py: {arm} block {i + 1}/{BLOCKS} done", file=sys.stderr)
    return plain, web, rates


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="udan-bench-web-") as tmp:
        plain, web, rates = asyncio.run(_measure(Path(tmp)))
    arms = {"plain": plain, "web": web}
    pool = {arm: np.concatenate([r.decisions_ns for r in runs]) for arm, runs in arms.items()}
    ratio, low, high = p99_ratio(plain, web)
    missed = {arm: sum(r.missed for r in runs) for arm, runs in arms.items()}
    sent = {arm: missed[arm] + sum(r.on_time for r in runs) for arm, runs in arms.items()}
    result = {
        "benchmark": "web",
        "blocks": BLOCKS,
        "block_s": BLOCK_S,
        "warm_up_s": WARM_UP_S,
        "clients": CLIENTS,
        "mode": "--realtime" if REALTIME else "SCHED_OTHER",
        "load_average_1m": round(os.getloadavg()[0], 2),
        "decisions": {arm: int(v.size) for arm, v in pool.items()},
        "decision_p50_ms": {arm: round(float(np.median(v)) / 1e6, 4) for arm, v in pool.items()},
        "decision_p99_ms": {arm: round(p99_ms(v), 4) for arm, v in pool.items()},
        "decision_p99_ms_per_block": {
            arm: [round(p99_ms(r.decisions_ns), 4) for r in runs] for arm, runs in arms.items()
        },
        "p99_ratio_web_to_plain": round(ratio, 4),
        "p99_ratio_ci95": [round(low, 4), round(high, 4)],
        "deadline_missed": missed,
        "commands": sent,
        "client_update_hz": {"min": min(rates, default=0.0), "median": float(np.median(rates))},
        "targets": {
            "p99_ratio_max": TARGET_RATIO,
            "deadline_missed": 0,
            "client_update_hz_min": TARGET_UPDATE_HZ,
        },
        "verdicts": {
            "p99_ratio": ratio <= TARGET_RATIO,
            "no_deadline_miss": missed["plain"] == 0 and missed["web"] == 0,
            "clients_attached": min(rates, default=0.0) >= TARGET_UPDATE_HZ,
        },
    }
    result["meets_target"] = all(result["verdicts"].values())
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
