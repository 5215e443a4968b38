"""The operator's web view: ``python -m udan.edge.web``, a process beside the control loop.

``udan-edge --web HOST:PORT`` starts it through :class:`udan.edge.sidecar.Outlet` (the loop's side
is :mod:`udan.edge.live`) and feeds it, never waiting for it: the run's configuration first (the
e-stop token travels there, never on a command line), then a snapshot at most every 100 ms (the
last step's record, the telemetry's running totals, the link's counters) and the camera's
thumbnail with its detections drawn. It serves (aiohttp, one asyncio loop, nicer than the edge):

- ``/``: the live page (static files shipped as package data, no build step), which opens
- ``/ws``: a WebSocket that gets the page's state as JSON at every snapshot (≤ 10 Hz) and the
  thumbnail as a binary JPEG message. Each client has a slot for the newest state and the newest
  image, and its own sender: a client that reads slowly skips states, and one that stops reading
  is dropped once a send has waited ``SEND_TIMEOUT_S`` (its socket's buffer is kept small), so
  nothing is buffered without bound and the other clients never wait for it.
- ``/metrics``: Prometheus text format, from ``prometheus_client``: a custom collector exposes
  the edge's own counts and histograms as they were in the last snapshot (counted once, in the
  edge's telemetry: ``/metrics`` and the run's report say the same).
- ``POST /estop``: the stop-all button. Only with a token (``udan-edge --web-token``), sent as
  ``Authorization: Bearer TOKEN``; the request goes back to the loop (:meth:`Inlet.reply`),
  which stops every car through the car protocol, authenticated per car like any command, and
  counts it. Refused requests are counted too; the token is never logged or shown.

Ends when the edge closes its end of the socket (however the edge ended).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hmac
import itertools
import json
import os
import socket
import sys
import threading
from collections.abc import Iterator, Sequence
from importlib import resources
from typing import Any

from aiohttp import WSMsgType, web
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.exposition import CONTENT_TYPE_LATEST

from udan.edge.sidecar import Inlet, ignore_interrupts

WEB_NICENESS = 10
"""The web process yields the CPU to the edge's loop (Unix niceness, higher is nicer)."""
SEND_TIMEOUT_S = 5.0
"""A client whose socket has taken nothing for this long is dropped."""
CLIENT_SNDBUF = 64 * 1024
"""Kernel send buffer per client: with the writer's limit, what a stalled client can hold up."""
WRITER_LIMIT = 64 * 1024
CLOSE_S = 1.0
"""At the end, how long the clients get to take the close (then they are cut off)."""
ESTOP_CONFIRM_S = 2.0
"""Longest a stop request waits for the edge to say how many cars it stopped."""
COMMAND_NAMES = ("up", "down", "left", "right", "wait", "stop")
SPANS = {  # the edge's histograms: metric name, what it measures
    "state_to_commands": ("udan_decision_latency_seconds", "Cells known to every command ready "
                          "(masking, grouping, inference, safety filter)"),
    "commands_to_received": ("udan_dispatch_latency_seconds", "Decision to the last car "
                             "received its command (the 10 ms dispatch deadline)"),
    "frame_to_received": ("udan_loop_latency_seconds", "Camera capture to the last car "
                          "received its command"),
    "frame_age": ("udan_frame_age_seconds", "Camera capture to the frame handed over by the "
                  "camera source (exposure, transfer, the driver's queue)"),
    "frame_to_state": ("udan_frame_to_state_seconds", "Camera capture to the cars' cells known "
                       "in the loop (vision and transfer)"),
    "vision": ("udan_vision_seconds", "Time the vision spent on a frame"),
}  # fmt: skip
PER_CAR = {  # per-car telemetry count, metric name (without _total), help
    "sent": ("udan_commands_sent", "Commands sent to a car"),
    "on_time": ("udan_commands_acked", "Commands a car accepted within their validity"),
    "late": ("udan_commands_late", "Commands that reached a car after their validity"),
    "missed": ("udan_commands_missed", "Commands a car did not accept in time"),
    "not_ready": ("udan_commands_not_ready", "Steps a car was not ready for (nothing sent)"),
}
COUNTS = {  # run-wide telemetry count, metric name (without _total), help
    "steps": ("udan_steps", "Decision steps dispatched"),
    "recentre_rounds": ("udan_recentre_rounds", "Re-centring rounds before a step (their "
                        "commands count in the per-car command counts)"),
    "frames": ("udan_frames", "Camera frames turned into cells"),
    "late_sends": ("udan_sends_late", "Sends not proven on time by the car (must stay 0)"),
    "late_executions": ("udan_executions_late", "Commands a car ran after their deadline "
                        "(must stay 0)"),
    "remote_estop": ("udan_remote_estops", "Emergency stops from the web page"),
}  # fmt: skip


def _static(name: str) -> bytes:
    return resources.files("udan.edge").joinpath("static", name).read_bytes()


class Client:
    """One WebSocket client: a slot for the newest state and one for the newest image, sent by
    its own task; dropped when a send cannot finish in ``SEND_TIMEOUT_S``."""

    def __init__(self, ws: web.WebSocketResponse, transport: asyncio.Transport) -> None:
        self.ws = ws
        self.transport = transport
        self._text: str | None = None
        self._image: bytes | None = None
        self._wake = asyncio.Event()
        self.dropped = False
        """It stopped reading and was cut off."""

    def push(self, text: str | None = None, image: bytes | None = None) -> None:
        """Newest wins: what the client has not been sent yet is replaced."""
        if text is not None:
            self._text = text
        if image is not None:
            self._image = image
        self._wake.set()

    async def run(self) -> None:
        """Send until the client goes, or drop it when it stops reading."""
        while not self.ws.closed:
            await self._wake.wait()
            self._wake.clear()
            text, self._text, image, self._image = self._text, None, self._image, None
            try:
                if text is not None:
                    await asyncio.wait_for(self.ws.send_str(text), SEND_TIMEOUT_S)
                if image is not None:
                    await asyncio.wait_for(self.ws.send_bytes(image), SEND_TIMEOUT_S)
            except TimeoutError:
                self.dropped = True
                self.transport.abort()
                return
            except (ConnectionError, RuntimeError):  # closed meanwhile
                return


class View:
    """What the web process knows: the run's configuration, the newest snapshot and
    thumbnail, the clients, its own counts."""

    def __init__(self, config: dict[str, Any], inlet: Inlet) -> None:
        self._token: str | None = config.pop("token", None)
        self.config = config
        self.inlet = inlet
        self.snapshot: dict[str, Any] | None = None
        self.page = json.dumps({"kind": "waiting"})
        self.thumbnail: bytes | None = None
        self.clients: set[Client] = set()
        self.counts = {"clients_dropped": 0, "estop_refused": 0}
        self._stops: dict[int, asyncio.Future[int]] = {}
        self._stop_ids = itertools.count(1)
        self.hello = json.dumps({"kind": "hello", **config, "estop": self._token is not None})

    # -- from the edge ---------------------------------------------------------------------
    def take(self, record: tuple) -> None:
        """One record from the edge (in the loop)."""
        kind, body = record
        if kind == "state":
            self.snapshot = body
            self.page = json.dumps(page_state(body, self.config))
            for client in self.clients:
                client.push(text=self.page)
        elif kind == "thumbnail":
            self.thumbnail = body
            for client in self.clients:
                client.push(image=body)
        elif kind == "estopped":
            future = self._stops.pop(body["id"], None)
            if future is not None and not future.done():
                future.set_result(body["cars"])

    # -- the stop-all button ---------------------------------------------------------------
    def authorised(self, header: str) -> bool | None:
        """None when the e-stop is off (no token), else whether ``header`` carries it."""
        if self._token is None:
            return None
        given = header.removeprefix("Bearer ").strip().encode()
        return hmac.compare_digest(given, self._token.encode())

    async def stop_all(self) -> int | None:
        """Ask the loop to stop every car; how many it sent the stop to, None if it did not
        say in time."""
        stop_id = next(self._stop_ids)
        future = asyncio.get_running_loop().create_future()
        self._stops[stop_id] = future
        if not self.inlet.reply({"kind": "estop", "id": stop_id}):
            self._stops.pop(stop_id, None)
            return None
        try:
            return await asyncio.wait_for(future, ESTOP_CONFIRM_S)
        except TimeoutError:
            self._stops.pop(stop_id, None)
            return None


def page_state(snapshot: dict[str, Any], config: dict[str, Any]) -> dict[str, Any]:
    """The page's JSON from an edge snapshot: the arena, the last step's cars and groups, link
    state per car, the decision latency histogram, the deadline counters."""
    step = snapshot.get("step") or {}
    totals = snapshot["totals"]
    counts, per_car = totals["counts"], totals["per_car"]
    joined = set(snapshot["joined"])
    uncertain = set(step.get("uncertain_cars", ()))
    commands, outcomes = step.get("commands", {}), step.get("outcomes", {})
    headings = step.get("headings_deg", {})
    groups = step.get("groups", [])
    leaders = {g[0] for g in groups}
    cars = []
    for car, cell in sorted(step.get("cells", {}).items(), key=lambda kv: int(kv[0])):
        command = commands.get(car)
        cars.append(
            {
                "id": int(car),
                "cell": cell,
                "heading": headings.get(car),
                "uncertain": int(car) in uncertain,
                "leader": int(car) in leaders,
                "command": None if command is None else COMMAND_NAMES[command],
                "outcome": outcomes.get(car),
            }
        )
    links = [
        {"id": car, "joined": car in joined, **{k: per_car.get(str(car), {}).get(k, 0)
                                                for k in ("sent", "on_time", "missed", "late")}}
        for car in config["cars"]
    ]  # fmt: skip
    decision = totals["histograms"]["state_to_commands"]
    at_most = decision["at_most"]
    sent = counts.get("on_time", 0) + counts.get("missed", 0)
    return {
        "kind": "state",
        "t_ns": str(snapshot["t_ns"]),
        "step_t_ns": str(step["t_ns"]) if step else None,
        "step": counts.get("steps", 0),
        "episodes": totals["episodes"],
        "static": snapshot["static"],
        "cars": cars,
        "groups": groups,
        "links": links,
        "fleet": snapshot["fleet"],
        "score": step.get("score"),
        "decision_ms": _ms(step.get("state_to_commands_ns")),
        "loop_ms": _ms(step.get("frame_to_received_ns")),
        "latency": {
            "le_ms": [ns / 1e6 for ns in decision["le_ns"]],
            "counts": [b - a for a, b in itertools.pairwise([0, *at_most])],
        },
        "deadline": {
            "on_time": counts.get("on_time", 0),
            "missed": counts.get("missed", 0),
            "late_sends": counts.get("late_sends", 0),
            "late_executions": counts.get("late_executions", 0),
            "share": counts.get("on_time", 0) / sent if sent else None,
        },
        "frames": counts.get("frames", 0),
        "frame_age_ms": _ms(snapshot.get("frame_age_ns")),
        "stopped": snapshot["stopped"],
        "remote_estops": counts.get("remote_estop", 0),
    }


def _ms(ns: int | None) -> float | None:
    return None if ns is None else round(ns / 1e6, 3)


class EdgeCollector:
    """``/metrics`` from the newest snapshot: the edge's counts and histograms, as counted by
    its telemetry (a custom collector: the values are the edge's, not counted again here)."""

    def __init__(self, view: View) -> None:
        self.view = view

    def collect(self) -> Iterator[Metric]:
        view, snapshot = self.view, self.view.snapshot
        clients = GaugeMetricFamily("udan_web_clients", "Live page clients connected")
        clients.add_metric([], len(view.clients))
        yield clients
        yield _counter("udan_web_clients_dropped", "Clients dropped for not reading",
                       view.counts["clients_dropped"])  # fmt: skip
        yield _counter("udan_web_estops_refused", "Stop requests without the right token",
                       view.counts["estop_refused"])  # fmt: skip
        if snapshot is None:
            return
        totals = snapshot["totals"]
        counts, histograms = totals["counts"], totals["histograms"]
        for name, (metric, text) in SPANS.items():
            h = histograms[name]
            buckets = [(_le(ns), n) for ns, n in zip(h["le_ns"], h["at_most"], strict=False)]
            buckets.append(("+Inf", h["at_most"][-1]))
            yield HistogramMetricFamily(metric, text, buckets=buckets, sum_value=h["sum_s"])
        for key, (metric, text) in COUNTS.items():
            yield _counter(metric, text, counts.get(key, 0))
        for key, (metric, text) in PER_CAR.items():
            family = CounterMetricFamily(metric, text, labels=["car"])
            for car in view.config["cars"]:
                family.add_metric([str(car)], totals["per_car"].get(str(car), {}).get(key, 0))
            yield family
        sightings = CounterMetricFamily(
            "udan_sightings", "Car markers seen on the grid, by whether they were placed in a "
            "cell", labels=["result"]
        )  # fmt: skip
        sightings.add_metric(["found"], counts.get("sightings_found", 0))
        sightings.add_metric(["uncertain"], counts.get("sightings_uncertain", 0))
        yield sightings
        camera = snapshot["camera"]
        yield _counter("udan_frames_dropped", "Frames whose scene the loop never got",
                       camera["dropped"])  # fmt: skip
        yield _counter("udan_frames_stale", "Frames skipped for waiting in a driver queue "
                       "longer than a frame period", camera.get("stale", 0))  # fmt: skip
        yield _counter("udan_frames_incomplete", "GenICam buffers dropped incomplete (lost "
                       "stream packets)", camera.get("incomplete", 0))  # fmt: skip
        yield _counter("udan_estop_frames", "Emergency stop frames sent to cars",
                       snapshot["link"].get("estops", 0))  # fmt: skip
        yield _counter("udan_live_records_dropped", "Snapshots the web view missed (it was "
                       "behind)", snapshot["live_dropped"])  # fmt: skip
        step = snapshot.get("step") or {}
        for metric, text, value in (
            ("udan_cars_present", "Cars in the fleet (joined and seen)", len(snapshot["fleet"])),
            ("udan_cars_joined", "Cars joined over the link", len(snapshot["joined"])),
            ("udan_groups", "Groups at the last step", len(step.get("groups", []))),
            ("udan_leaders", "Group leaders at the last step",
             len({g[0] for g in step.get("groups", [])})),
            ("udan_newest_frame_age_seconds", "Age of the newest frame the loop has", _s(
                snapshot.get("frame_age_ns"))),
            ("udan_score", "Average return of the episode so far", step.get("score")),
            ("udan_stopped", "1 once every car has been sent an emergency stop",
             int(snapshot["stopped"])),
        ):  # fmt: skip
            if value is not None:
                gauge = GaugeMetricFamily(metric, text)
                gauge.add_metric([], value)
                yield gauge


def _counter(name: str, text: str, value: float) -> CounterMetricFamily:
    family = CounterMetricFamily(name, text)
    family.add_metric([], value)
    return family


def _le(ns: int) -> str:
    return f"{ns / 1e9:g}"


def _s(ns: int | None) -> float | None:
    return None if ns is None else ns / 1e9


def build_app(view: View) -> web.Application:
    """The routes (see the module docstring)."""
    registry = CollectorRegistry(auto_describe=True)
    registry.register(EdgeCollector(view))

    async def index(_request: web.Request) -> web.Response:
        return web.Response(body=_static("index.html"), content_type="text/html")

    async def asset(request: web.Request) -> web.Response:
        name = request.match_info["name"]
        types = {"app.js": "text/javascript", "style.css": "text/css"}
        if name not in types:
            raise web.HTTPNotFound()
        return web.Response(body=_static(name), content_type=types[name])

    async def metrics(_request: web.Request) -> web.Response:
        body = generate_latest(registry)
        return web.Response(body=body, headers={"Content-Type": CONTENT_TYPE_LATEST})

    async def estop(request: web.Request) -> web.Response:
        allowed = view.authorised(request.headers.get("Authorization", ""))
        if allowed is None:
            view.counts["estop_refused"] += 1
            return web.json_response(
                {"error": "the e-stop is off: start udan-edge with --web-token"}, status=403
            )
        if not allowed:
            view.counts["estop_refused"] += 1
            return web.json_response({"error": "wrong or missing token"}, status=401)
        cars = await view.stop_all()
        if cars is None:
            return web.json_response({"error": "the edge did not confirm the stop"}, status=504)
        return web.json_response({"stopped": True, "cars": cars})

    async def socket_handler(request: web.Request) -> web.WebSocketResponse:
        transport = request.transport
        assert transport is not None
        sock = transport.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, CLIENT_SNDBUF)
        ws = web.WebSocketResponse(compress=False, writer_limit=WRITER_LIMIT)
        await ws.prepare(request)
        client = Client(ws, transport)
        await ws.send_str(view.hello)
        client.push(text=view.page, image=view.thumbnail)
        view.clients.add(client)
        sender = asyncio.ensure_future(client.run())
        try:
            async for message in ws:  # the page sends nothing; this notices it leave
                if message.type == WSMsgType.ERROR:
                    break
        finally:
            view.clients.discard(client)
            view.counts["clients_dropped"] += client.dropped
            sender.cancel()
        return ws

    app = web.Application()
    app.add_routes(
        [
            web.get("/", index),
            web.get("/static/{name}", asset),
            web.get("/metrics", metrics),
            web.post("/estop", estop),
            web.get("/ws", socket_handler),
        ]
    )
    return app


async def serve(inlet: Inlet, host: str, port: int) -> int:
    """Bind, say ready (or the error, one line), then serve until the edge goes."""
    records = iter(inlet)
    kind, config = next(records, ("end", None))
    if kind != "config":
        return 0
    view = View(config, inlet)
    try:
        listening = socket.create_server((host, port))
    except OSError as err:
        reason = os.strerror(err.errno) if err.errno else str(err)
        inlet.reply({"kind": "error", "message": f"--web {host}:{port}: {reason}"})
        return 2
    runner = web.AppRunner(
        build_app(view), access_log=None, handle_signals=False, shutdown_timeout=CLOSE_S
    )
    await runner.setup()
    await web.SockSite(runner, listening).start()
    bound = listening.getsockname()  # port 0: the one the kernel chose
    inlet.reply({"kind": "ready", "url": f"http://{_host(bound[0])}:{bound[1]}/"})
    loop = asyncio.get_running_loop()
    ended = asyncio.Event()

    def read() -> None:  # the socket blocks: read it in a thread, hand records to the loop
        for record in records:
            loop.call_soon_threadsafe(view.take, record)
        loop.call_soon_threadsafe(ended.set)

    threading.Thread(target=read, name="edge records", daemon=True).start()
    try:
        await ended.wait()
    finally:
        await asyncio.gather(*(_close(client) for client in list(view.clients)))
        await runner.cleanup()
    return 0


async def _close(client: Client) -> None:
    """Say goodbye to a client; cut off one that does not take it within ``CLOSE_S``."""
    try:
        await asyncio.wait_for(client.ws.close(), CLOSE_S)
    except (TimeoutError, ConnectionError):
        client.transport.abort()


def _host(address: str) -> str:
    return f"[{address}]" if ":" in address else address


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m udan.edge.web --fd N --bind HOST:PORT`` (started by the edge, not by hand)."""
    parser = argparse.ArgumentParser(prog="udan.edge.web", description=__doc__)
    parser.add_argument("--fd", type=int, required=True)
    parser.add_argument("--bind", required=True)
    args = parser.parse_args(argv)
    ignore_interrupts()
    with contextlib.suppress(OSError):
        os.nice(WEB_NICENESS)
    host, _, port = args.bind.rpartition(":")
    inlet = Inlet(args.fd)
    try:
        return asyncio.run(serve(inlet, host.strip("[]"), int(port)))
    finally:
        inlet.close()


if __name__ == "__main__":
    sys.exit(main())
