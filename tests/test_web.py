"""``udan-edge --web``: the live page in a real headless Chromium, ``/metrics`` against the run's
own record, the stop-all button with and without its token, a client that stops reading, and
bad input. Chromium is Debian's (``make`` installs it); Playwright drives it."""

from __future__ import annotations

import asyncio
import json
import os
import re
import secrets
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import cv2
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families
from test_edge_cli import _ask, _world_and_edge

from udan.edge.live import web_address
from udan.edge.web import COMMAND_NAMES
from udan.fleetfile import write_fleet
from udan.models import bundled_policy

ROOT = Path(__file__).resolve().parents[1]
UDAN_EDGE = str(Path(sys.executable).with_name("udan-edge"))
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]  # fmt: skip
URL_LINE = re.compile(r"^udan-edge: live view at (http://\S+/)$")
TOKEN = f"test-{secrets.token_urlsafe(18)}"  # fresh every session: found only if it leaked
# every metric the issue names, and the web process's own
METRICS = {
    "udan_decision_latency_seconds", "udan_dispatch_latency_seconds", "udan_loop_latency_seconds",
    "udan_frame_to_state_seconds", "udan_vision_seconds", "udan_newest_frame_age_seconds",
    "udan_frame_age_seconds", "udan_frames_stale", "udan_frames_incomplete",
    "udan_commands_sent", "udan_commands_acked", "udan_commands_late", "udan_commands_missed",
    "udan_commands_not_ready", "udan_cars_present", "udan_cars_joined", "udan_sightings",
    "udan_groups", "udan_leaders", "udan_steps", "udan_recentre_rounds", "udan_frames",
    "udan_frames_dropped",
    "udan_sends_late", "udan_executions_late", "udan_remote_estops", "udan_estop_frames",
    "udan_score", "udan_stopped", "udan_web_clients", "udan_web_clients_dropped",
    "udan_web_estops_refused", "udan_live_records_dropped",
}  # fmt: skip


def test_chromium_is_installed_by_the_project_setup() -> None:
    assert Path(CHROMIUM).is_file(), "make installs Debian's chromium (apt-get install chromium)"


@dataclass
class Run:
    proc: subprocess.Popen
    url: str
    telemetry: Path
    report: Path


def _url(proc: subprocess.Popen) -> str:
    line = proc.stdout.readline().strip()
    match = URL_LINE.match(line)
    if match is None:
        proc.kill()
        raise AssertionError(f"no live view: {line!r} {proc.stderr.read()}")
    return match.group(1)


def _stop(proc: subprocess.Popen) -> tuple[str, str]:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    return out, err


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Run]:
    """``udan-edge --sim --web`` with 5 cars, no token (the stop button is off)."""
    folder = tmp_path_factory.mktemp("web")
    telemetry, report = folder / "telemetry.jsonl", folder / "report.json"
    env = {k: v for k, v in os.environ.items() if k != "UDAN_WEB_TOKEN"}
    proc = subprocess.Popen(
        [
            UDAN_EDGE, "--sim", "--cars", "5", "--duration", "120", "--web", "127.0.0.1:0",
            "--quiet", "--telemetry", str(telemetry), "--report", str(report),
        ],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    try:
        yield Run(proc, _url(proc), telemetry, report)
    finally:
        _stop(proc)


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """A real headless Chromium (Debian's), a fresh profile."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        context = playwright.chromium.launch_persistent_context(
            str(tmp_path_factory.mktemp("chromium-profile")),
            executable_path=CHROMIUM,
            headless=True,
            args=CHROMIUM_ARGS,
            viewport={"width": 1400, "height": 900},
        )
        try:
            yield context
        finally:
            context.close()


def _records(path: Path, *kinds: str) -> list[dict[str, Any]]:
    """The complete lines of ``kinds`` written so far, in order (the edge flushes once a
    second)."""
    if not path.exists():
        return []
    lines = path.read_text().split("\n")[:-1]  # the last may be half written
    return [r for r in map(json.loads, lines) if r["kind"] in kinds]


def _wait(check: Callable[[], Any], timeout_s: float = 30.0, what: str = "") -> Any:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if value := check():
            return value
        time.sleep(0.1)
    raise AssertionError(f"waited {timeout_s} s for {what}")


def _metrics(url: str) -> dict[str, Any]:
    text = urllib.request.urlopen(url + "metrics", timeout=10).read().decode()
    return {family.name: family for family in text_string_to_metric_families(text)}


def _value(families: dict[str, Any], name: str, **labels: str) -> float:
    (sample,) = [s for s in families[name].samples if s.labels == labels]
    return sample.value


SHOWN = """() => {
  const svg = document.getElementById("arena");
  return {
    stepT: svg.dataset.stepT,
    groups: svg.querySelectorAll("line.group").length,
    cars: [...svg.querySelectorAll("g.car")].map((g) => ({
      id: +g.dataset.car, row: +g.dataset.row, col: +g.dataset.col, command: g.dataset.command,
      leader: g.dataset.leader === "true"})),
  };
}"""


def test_the_page_shows_every_car_of_the_fleet_in_the_cell_the_step_decided_on(sim, browser):
    page = browser.new_page()
    page.goto(sim.url)
    page.wait_for_function("document.querySelectorAll('#arena g.car').length > 0")
    # the camera thumbnail, with the detections drawn, from the perception process
    page.wait_for_function("document.getElementById('camera').naturalWidth === 480")
    page.wait_for_timeout(3000)  # a few seconds of updates
    shown = page.evaluate(SHOWN)  # one render's state: the page redraws at every update
    status = page.inner_text("#status")
    step = _wait(
        lambda: [r for r in _records(sim.telemetry, "step") if str(r["t_ns"]) == shown["stepT"]],
        what="the step the page shows in the telemetry",
    )[0]
    assert len(shown["cars"]) == step["cars"] == len(step["cells"]) >= 1
    assert {c["id"]: [c["row"], c["col"]] for c in shown["cars"]} == {
        int(car): cell for car, cell in step["cells"].items()
    }
    assert {c["id"]: c["command"] for c in shown["cars"]} == {
        int(car): COMMAND_NAMES[a] for car, a in step["commands"].items()
    }
    assert {c["id"] for c in shown["cars"] if c["leader"]} == {g[0] for g in step["groups"]}
    assert shown["groups"] == sum(len(g) - 1 for g in step["groups"])
    updates = float(re.match(r"live, ([\d.]+) updates/s", status).group(1))
    assert updates >= 2.0, status  # ~10 on a quiet machine; a loaded one delays the niced server
    links = page.inner_text("#links")
    assert all(f"\n{car}\t" in f"\n{links}" for car in range(1, 6)), links
    screenshot = ROOT / "out" / "web" / "live-page.png"
    screenshot.parent.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(screenshot), full_page=True)
    assert screenshot.stat().st_size > 10_000
    page.close()


def test_metrics_parse_and_say_what_the_run_recorded(sim):
    """/metrics, parsed by prometheus_client's own parser, against the telemetry the edge
    wrote: every count and bucket equals what the records up to that snapshot add up to."""

    def five_steps() -> dict[str, Any] | None:
        families = _metrics(sim.url)
        steps = _value(families, "udan_steps") if "udan_steps" in families else 0
        return families if steps >= 5 else None

    families = _wait(five_steps, what="five steps")
    assert families.keys() >= METRICS, METRICS - families.keys()
    # the Grafana dashboard in docs/ asks for nothing /metrics does not have
    dashboard = (ROOT / "docs" / "grafana-dashboard.json").read_text()
    asked = {
        re.sub(r"_(bucket|count|sum|total)$", "", m) for m in re.findall(r"udan_\w+", dashboard)
    }
    asked.discard("udan_edge")  # the dashboard's own name
    assert asked and asked <= families.keys(), asked - families.keys()
    steps, frames = int(_value(families, "udan_steps")), int(_value(families, "udan_frames"))
    rounds = int(_value(families, "udan_recentre_rounds"))

    def commanded() -> list[dict[str, Any]] | None:
        """The step and re-centring records in the order written, up to the snapshot's
        counts of each (a round's commands count in the per-car counts too)."""
        taken, seen = [], Counter()
        for r in _records(sim.telemetry, "step", "recentre"):
            if seen[r["kind"]] < {"step": steps, "recentre": rounds}[r["kind"]]:
                seen[r["kind"]] += 1
                taken.append(r)
        return taken if seen == Counter(step=steps, recentre=rounds) else None

    records = _wait(commanded, what="the records of the snapshot's steps and rounds")
    step_records = [r for r in records if r["kind"] == "step"]
    frame_records = _wait(lambda: len(r := _records(sim.telemetry, "frame")) >= frames and r)
    frame_records = frame_records[:frames]
    per_car: dict[str, Counter] = {str(car): Counter() for car in range(1, 6)}
    for r in records:
        for car, outcome in r["outcomes"].items():
            per_car[car][outcome] += 1
    for r in step_records:
        for car, sends in r["sends"].items():
            per_car[car]["sent"] += sends > 0
        for car in r["late_cars"]:
            per_car[str(car)]["late"] += 1
    for metric, key in (("udan_commands_sent", "sent"), ("udan_commands_acked", "on_time"),
                        ("udan_commands_missed", "missed"), ("udan_commands_late", "late"),
                        ("udan_commands_not_ready", "not_ready")):  # fmt: skip
        for car, counts in per_car.items():
            assert _value(families, metric, car=car) == counts[key], (metric, car)
    assert sum(_value(families, "udan_commands_sent", car=c) for c in per_car) > 0
    for metric, key, records in (
        ("udan_decision_latency_seconds", "state_to_commands_ns", step_records),
        ("udan_dispatch_latency_seconds", "commands_to_received_ns", step_records),
        ("udan_loop_latency_seconds", "frame_to_received_ns", step_records),
        ("udan_vision_seconds", "vision_ns", frame_records),
        ("udan_frame_to_state_seconds", "frame_to_state_ns", frame_records),
    ):
        values = [r[key] for r in records if r[key] is not None and r[key] >= 0]
        samples = families[metric].samples
        les = [float(s.labels["le"]) for s in samples if s.name.endswith("_bucket")]
        assert 0.01 in les  # the dispatch deadline is a bucket edge
        for s in samples:
            if s.name.endswith("_bucket"):
                le = float(s.labels["le"])
                at_most = len(values) if le == float("inf") else sum(v <= le * 1e9 for v in values)
                assert s.value == at_most, (metric, le)
            elif s.name.endswith("_count"):
                assert s.value == len(values)
            elif s.name.endswith("_sum"):
                assert s.value == pytest.approx(sum(values) / 1e9, rel=1e-9)
    assert _value(families, "udan_sightings", result="found") == sum(
        r["seen"] - r["uncertain"] for r in frame_records
    )
    assert _value(families, "udan_sightings", result="uncertain") == sum(
        r["uncertain"] for r in frame_records
    )
    last = step_records[-1]
    assert _value(families, "udan_groups") == len(last["groups"])
    assert _value(families, "udan_leaders") == len({g[0] for g in last["groups"]})
    assert _value(families, "udan_sends_late") == sum(r["late_sends"] for r in step_records)
    assert 1 <= _value(families, "udan_cars_present") <= 5
    assert _value(families, "udan_stopped") == 0
    assert 0 <= _value(families, "udan_newest_frame_age_seconds") < 5


def test_the_stop_button_is_off_without_a_token(sim, browser):
    page = browser.new_page()
    page.goto(sim.url)
    page.wait_for_function("document.querySelectorAll('#arena g.car').length > 0")
    assert page.is_disabled("#estop")
    page.close()
    request = urllib.request.Request(sim.url + "estop", method="POST")
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(request, timeout=10)
    assert refused.value.code == 403
    families = _metrics(sim.url)
    assert _value(families, "udan_web_estops_refused") >= 1
    assert _value(families, "udan_stopped") == 0 and _value(families, "udan_remote_estops") == 0


def _handshake(port: int) -> socket.socket:
    """A WebSocket client that reads the handshake and then nothing more, with a tiny receive
    buffer (a browser tab frozen in the background, a client on a dead link)."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", port))
    sock.sendall(
        b"GET /ws HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    assert sock.recv(12) == b"HTTP/1.1 101"
    return sock


def _cut_off(sock: socket.socket) -> bool:
    """Whether the server has closed ``sock``: what it had sent reads out, then the end."""
    sock.settimeout(10)
    try:
        while sock.recv(65536):
            pass
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False  # still open, nothing more coming
    return True


def test_a_client_that_stops_reading_is_dropped_and_the_others_keep_their_updates(sim):
    port = int(sim.url.rsplit(":", 1)[1].strip("/"))
    before = _value(_metrics(sim.url), "udan_web_clients_dropped")
    done = threading.Event()

    async def reader() -> tuple[int, float]:
        """A client that reads: the states it gets until the other one is dropped."""
        states, start = 0, time.monotonic()
        async with aiohttp.ClientSession() as session, session.ws_connect(sim.url + "ws") as ws:
            while not done.is_set() and time.monotonic() - start < 60:
                try:
                    message = await ws.receive(timeout=0.5)
                except TimeoutError:
                    continue
                states += message.type == aiohttp.WSMsgType.TEXT
        return states, time.monotonic() - start

    stalled = _handshake(port)
    try:
        with ThreadPoolExecutor(1) as pool:  # Playwright's loop runs in this thread
            reading = pool.submit(asyncio.run, reader())
            try:
                _wait(
                    lambda: _value(_metrics(sim.url), "udan_web_clients_dropped") > before,
                    45.0, "the stalled client to be dropped",
                )  # fmt: skip
            finally:
                done.set()
            states, seconds = reading.result()
        assert _cut_off(stalled)
    finally:
        stalled.close()
    assert _value(_metrics(sim.url), "udan_web_clients_dropped") == before + 1
    # ~10 a second on a quiet machine while the other client stalled and was dropped
    assert states >= 2 * seconds, (states, seconds)


def _camera_folder(folder: Path) -> str:
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i}.png"), np.full((120, 160), 128, np.uint8))
    return str(folder)


@pytest.mark.parametrize(
    ("web", "token", "message"),
    [
        ("0.0.0.0:0", None, "needs --web-token"),
        ("192.168.1.20:8080", None, "needs --web-token"),
        ("127.0.0.1:0", "short", "at least 16 characters"),
        ("localhost:http", None, "--web must be HOST:PORT"),
    ],
)
def test_bad_web_options_are_one_line_and_exit_2(tmp_path, web, token, message):
    env = {k: v for k, v in os.environ.items() if k != "UDAN_WEB_TOKEN"}
    if token is not None:
        env["UDAN_WEB_TOKEN"] = token
    done = subprocess.run(
        [UDAN_EDGE, "--sim", "--duration", "5", "--web", web],
        capture_output=True, text=True, timeout=60, env=env,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and message in done.stderr, done.stderr
    if token is not None:
        assert token not in done.stdout + done.stderr


def test_a_port_alone_is_served_on_loopback() -> None:
    assert web_address("8080", None) == ("127.0.0.1", 8080)
    assert web_address("[::1]:8080", None) == ("::1", 8080)


def test_a_port_in_use_is_one_line_and_exit_2(tmp_path):
    fleet = write_fleet(tmp_path / "fleet.toml", 2)
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        done = subprocess.run(
            [
                UDAN_EDGE, "--camera", _camera_folder(tmp_path / "frames"),
                "--model", str(bundled_policy()), "--fleet", str(fleet),
                "--listen", "127.0.0.1:0", "--web", f"127.0.0.1:{port}", "--duration", "5",
            ],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert done.stderr == f"udan-edge: error: --web 127.0.0.1:{port}: Address already in use\n"


def test_the_stop_button_with_its_token_stops_every_car_through_the_car_protocol(tmp_path, browser):
    """Without the token or with a wrong one: refused and counted, the cars drive on. With it,
    from the page: every car latches the protocol's emergency stop while the edge still runs,
    no step follows, and the stop is counted. The token shows nowhere."""
    fleet = write_fleet(tmp_path / "fleet.toml", 2)
    env = {**os.environ, "UDAN_WEB_TOKEN": TOKEN}
    telemetry = tmp_path / "telemetry.jsonl"
    extra = ["--web", "127.0.0.1:0", "--telemetry", str(telemetry)]
    with _world_and_edge(tmp_path, fleet, extra, env) as (control, edge, _camera):
        url = _url(edge)
        for header in ({}, {"Authorization": "Bearer not-the-token-at-all"}):
            request = urllib.request.Request(url + "estop", method="POST", headers=header)
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(request, timeout=10)
            assert refused.value.code == 401
        cars = _ask(control, {"op": "cars"})["cars"]
        assert not any(c["estopped"] for c in cars.values())
        page = browser.new_page()
        page.goto(url)
        page.wait_for_function("!document.getElementById('estop').disabled")
        page.fill("#token", TOKEN)
        page.click("#estop")
        page.wait_for_function(
            "document.getElementById('estop-result').textContent.startsWith('stop sent')"
        )
        assert page.inner_text("#estop-result") == "stop sent to 2 car(s)"
        cars = _ask(control, {"op": "cars"})["cars"]
        assert all(c["estopped"] for c in cars.values()), cars
        assert edge.poll() is None  # the stop came from the page, not from the edge's exit
        page.wait_for_function("document.getElementById('status').textContent.startsWith('STOP')")
        html = page.content()
        page.close()
        families = _metrics(url)
        steps = _value(families, "udan_steps")
        time.sleep(1.0)
        families = _metrics(url)
        metrics_text = urllib.request.urlopen(url + "metrics", timeout=10).read().decode()
        assert _value(families, "udan_steps") == steps  # no step after the stop
        assert _value(families, "udan_remote_estops") == 1
        assert _value(families, "udan_web_estops_refused") == 2
        assert _value(families, "udan_stopped") == 1
        static = "".join(
            urllib.request.urlopen(url + path, timeout=10).read().decode()
            for path in ("", "static/app.js", "static/style.css")
        )
        out, err = _stop(edge)
    report = json.loads((tmp_path / "edge.json").read_text())
    assert report["counts"]["remote_estop"] == 1
    assert report["link"]["estops"] >= 2  # one frame per car at least, authenticated per car
    for text in (out, err, json.dumps(report), telemetry.read_text(), html, metrics_text, static):
        assert TOKEN not in text
