"""udan-edge: drive a fleet from a camera with an exported policy.

    udan-edge --camera /dev/video0 --model policy.onnx --fleet fleet.toml [--transport udp]
    udan-edge --camera "aravis://192.168.1.20?width=1920&height=1200&fps=40" ...
    udan-edge --sim [--cars 5] [--duration 30]      # virtual camera + mock fleet, bundled policy
    udan-edge ... --record run.mcap                 # a flight recording of the run
    udan-edge --replay run.mcap [--model other.onnx] [--vision]   # its decisions again

``--sim`` starts the HIL world (``python -m udan.hil.world``: simulated arena, mock cars on loopback
UDP, the virtual camera) as its own process and drives it with this same runtime; the edge
never imports it. ``--record`` writes the run's flight recording off the loop
(:mod:`udan.edge.recorder`); ``--replay`` feeds one to a new control core (:mod:`udan.edge.replay`)
with no camera and no car. Bad input — a missing or corrupt model, a camera that cannot be opened
or refuses its mode, a malformed fleet file, a transport that cannot be bound, a file that is not
a flight recording, a model for another task — is one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import hashlib
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from udan.edge.calibration import VisionError
from udan.edge.camera import CameraError, FrameGrabber, open_camera
from udan.edge.core import ControlCore, MotionRules
from udan.edge.decide import DecisionStep, TaskError, task_of
from udan.edge.episodes import EpisodePlan, EpisodePlayer, WorldError
from udan.edge.fleet import Fleet
from udan.edge.flightlog import FlightLogError
from udan.edge.geometry import ArenaGeometry
from udan.edge.link import CarLink
from udan.edge.live import MIN_TOKEN_CHARS, LiveView, WebError, web_address
from udan.edge.overlay import OverlaySettings
from udan.edge.pauses import freeze_garbage, run_realtime, scheduler
from udan.edge.perception import (
    FrameRing,
    Perception,
    PerceptionError,
    ProcessPerception,
    RingSpec,
    ThreadPerception,
    VisionSettings,
)
from udan.edge.recorder import DEFAULT_QUALITY, DEFAULT_RATE, FlightRecorder
from udan.edge.replay import ReplayError
from udan.edge.shell import EdgeShell, LoopConfig
from udan.edge.sidecar import exit_with_parent, parent_watch_env
from udan.edge.telemetry import DEADLINE_NS, Telemetry
from udan.edge.transport import TransportError, free_udp_port, host_port, open_transport
from udan.envs.errors import OneLineParser
from udan.export.metadata import MetadataError, obs_spec, project_version
from udan.fleetfile import CarEntry, FleetFileError, load_fleet, write_fleet
from udan.models import DEFAULT_POLICY, bundled_policy

PROG = "udan-edge"
SIM_MARKER_BASE = 10
WEB_TOKEN_ENV = "UDAN_WEB_TOKEN"


class UsageError(ValueError):
    """A bad option or input, reported in one line."""


class _Interrupts:
    """SIGINT and SIGTERM outside the run (the runtime takes them over while it drives) raise
    ``KeyboardInterrupt``, so the ``finally`` blocks stop what was started: the ``--sim``
    world, the link. Between ``hold`` and ``release`` one is kept for later instead."""

    def __init__(self) -> None:
        self._holding = False
        self._held = False

    def install(self) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._interrupt)

    def _interrupt(self, _signum: int, _frame: object) -> None:
        if self._holding:
            self._held = True
            return
        raise KeyboardInterrupt

    def hold(self) -> None:
        self._holding = True

    def release(self, *, raise_held: bool = True) -> None:
        """Stop holding; raise the interruption that came meanwhile, if one did."""
        self._holding = False
        held, self._held = self._held, False
        if held and raise_held:
            raise KeyboardInterrupt


INTERRUPTS = _Interrupts()


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog=PROG, description=__doc__.split("\n\n")[0])
    src = p.add_argument_group("what to drive")
    src.add_argument("--sim", action="store_true", help="virtual camera + mock fleet (HIL world)")
    src.add_argument(
        "--camera", help="/dev/videoN, an index, aravis://DEVICE, a video file, a folder, "
        "virtual://N; a live camera's mode as ?width=W&height=H&fps=F&format=...&exposure_us=..."
        "&gain=...&strict=1 (docs/lab-setup.md)",
    )  # fmt: skip
    src.add_argument("--model", type=Path, help="exported policy (default with --sim: the bundled "
                     f"{DEFAULT_POLICY} policy)")  # fmt: skip
    src.add_argument("--fleet", type=Path, help="fleet.toml: car id, marker, address, key")
    src.add_argument("--calibration", help="OpenCV camera calibration YAML (undistortion)")
    link = p.add_argument_group("link to the cars")
    link.add_argument("--transport", default="udp", help="udp (default), serial or can")
    link.add_argument("--listen", default="0.0.0.0:9000", help="udp: HOST:PORT to listen on")
    link.add_argument("--can-interface", default="socketcan", help="can: python-can interface")
    link.add_argument("--can-channel", default="vcan0", help="can: channel")
    run = p.add_argument_group("run")
    run.add_argument("--duration", type=float, help="seconds to run (default: until Ctrl-C)")
    run.add_argument("--step-timeout", type=float, default=1.0, help="longest step wait (s)")
    run.add_argument("--lost", type=float, default=0.5, help="a car unseen this long leaves (s)")
    run.add_argument(
        "--settle-mm", type=float, default=30.0,
        help="a car farther than this from its cell's centre is re-centred before a step",
    )  # fmt: skip
    run.add_argument(
        "--settle-deg", type=float, default=5.0,
        help="... or turned farther than this from facing up",
    )  # fmt: skip
    run.add_argument(
        "--body-mm", type=float, default=220.0,
        help="side of the cars' (square) bodies: how close two may come (docs/motion.md)",
    )  # fmt: skip
    run.add_argument(
        "--cell-time-ms", type=float, default=200.0,
        help="the cars' time per cell (with --sim: the mock cars'): the guard predicts their "
        "moves with it (docs/motion.md)",
    )  # fmt: skip
    run.add_argument(
        "--accel-share", type=float, default=0.25,
        help="the cars' speed profile: share of a move's time spent accelerating, as long "
        "braking (0: constant speed, as the --sim cars)",
    )  # fmt: skip
    run.add_argument("--world", help="HIL world control HOST:PORT: play its episodes")
    run.add_argument("--episodes", type=int, help="with --world: episodes to play")
    run.add_argument("--episode-steps", type=int, default=50, help="decisions per episode")
    run.add_argument(
        "--perception", choices=("process", "thread"), default="process",
        help="camera and vision in a process of their own (default) or in threads of this one",
    )  # fmt: skip
    run.add_argument(
        "--realtime", action="store_true", help="event loop at real-time priority (SCHED_RR; "
        "needs root or CAP_SYS_NICE)"
    )  # fmt: skip
    out = p.add_argument_group("output")
    out.add_argument("--report", type=Path, help="write the totals as JSON here at exit")
    out.add_argument("--telemetry", type=Path, help="write per-frame/per-step JSON lines here")
    out.add_argument("--quiet", action="store_true", help="no live summary line")
    out.add_argument(
        "--video", type=Path, help="record the camera to this MP4 with what the controller "
        "thinks drawn on it: cars, cells, groups, leaders, commands, score, latency",
    )  # fmt: skip
    out.add_argument(
        "--web", metavar="HOST:PORT", help="serve the live page and Prometheus /metrics here "
        "(a port alone is on 127.0.0.1; port 0 picks a free one); off by default",
    )  # fmt: skip
    out.add_argument(
        "--web-token", default=os.environ.get(WEB_TOKEN_ENV), metavar="TOKEN",
        help=f"enables the page's stop-all button for whoever gives this token (at least "
        f"{MIN_TOKEN_CHARS} characters; needed for a non-loopback --web; default: "
        f"${WEB_TOKEN_ENV}, which keeps it off the process list)",
    )  # fmt: skip
    rec = p.add_argument_group("flight recorder")
    rec.add_argument("--record", type=Path, help="write the run's flight recording (MCAP) here")
    rec.add_argument(
        "--record-rate", type=float, default=DEFAULT_RATE,
        help="frames a second recorded besides the ones decisions used (JPEG; 0: none)",
    )  # fmt: skip
    rec.add_argument(
        "--record-quality", default=str(DEFAULT_QUALITY),
        help="JPEG quality of those (1-100), or lossless",
    )  # fmt: skip
    rec.add_argument(
        "--replay", type=Path, help="replay a recording's decisions (with --model: another "
        "policy's) through the control core; no camera, no car",
    )  # fmt: skip
    rec.add_argument(
        "--vision", action="store_true",
        help="with --replay: run the vision again on the recorded frames and compare",
    )  # fmt: skip
    rec.add_argument(
        "--still", type=Path, help="with --replay --vision: a recorded frame, its sightings drawn "
        "(PNG)",
    )  # fmt: skip
    sim = p.add_argument_group("--sim")
    sim.add_argument("--cars", type=int, default=5, help="mock cars (1-5)")
    sim.add_argument("--obstacles", default="0-9", help="obstacles per episode, a range")
    sim.add_argument("--seed", type=int, default=0, help="episode layouts")
    return p


def _half_cell_m() -> float:
    """Half a cell's side (metres): a car farther than that off centre is in another cell."""
    return ArenaGeometry().cell_m / 2


def _writable(path: Path | None, what: str) -> None:
    if path is not None and not path.resolve().parent.is_dir():
        raise UsageError(f"{what} {path}: folder {path.resolve().parent} does not exist")


def load_policy(path: Path, geometry: ArenaGeometry) -> tuple[Any, DecisionStep]:
    """The ONNX policy and its decision step; refuses a model the edge cannot drive cars with."""
    from udan.export.runtime import OnnxPolicy

    if not path.is_file():
        raise UsageError(f"model {path}: no such file")
    try:
        policy = OnnxPolicy(path)
    except MetadataError as err:
        raise UsageError(f"model {path}: {err}") from None
    except Exception as err:  # onnxruntime raises its own types for a corrupt file
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise UsageError(f"model {path}: cannot be loaded by onnxruntime: {first}") from None
    task = task_of(policy.graph.metadata["env"])  # first: a MAgent policy sees no cars at all
    spec = obs_spec(policy.graph.metadata)
    if (spec.height, spec.width) != (geometry.rows, geometry.cols):
        raise UsageError(
            f"model {path} was trained on a {spec.height}x{spec.width} arena; "
            f"this arena is {geometry.rows}x{geometry.cols}"
        )
    return policy, DecisionStep(policy, task, spec)


def _transport_options(args: argparse.Namespace) -> dict[str, Any]:
    if args.transport == "udp":
        return {"listen": args.listen}
    if args.transport == "can":
        return {"interface": args.can_interface, "channel": args.can_channel}
    return {}


def code_version() -> str:
    """The package's version, and the git commit of its source tree when it is one."""
    try:
        commit = subprocess.run(
            ["git", "-C", str(Path(__file__).parent), "describe", "--always", "--dirty"],
            capture_output=True, text=True, timeout=5,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        commit = ""
    return f"{project_version()} ({commit})" if commit else project_version()


def _recording_meta(
    args: argparse.Namespace,
    policy: Any,
    task: str,
    settings: VisionSettings,
    cars: list[CarEntry],
    perception: Perception,
    config: LoopConfig,
    motion: MotionRules,
) -> dict[str, Any]:
    """The run's metadata for its flight recording (no key of any car: ids, markers and
    addresses only)."""
    calibration = args.calibration
    return {
        "code_version": code_version(),
        "realtime_ns": time.time_ns(),
        "monotonic_ns": time.monotonic_ns(),
        "model": str(args.model.resolve()),
        "model_sha256": hashlib.sha256(args.model.read_bytes()).hexdigest(),
        "env": policy.graph.metadata["env"],
        "task": task,
        "calibration_file": None if calibration is None else str(Path(calibration).resolve()),
        "calibration_sha256": None
        if calibration is None
        else hashlib.sha256(Path(calibration).read_bytes()).hexdigest(),
        "camera": perception.camera_info,
        "fleet": [
            {
                "id": c.car_id,
                "marker": c.marker,
                "address": None if c.address is None else f"{c.address[0]}:{c.address[1]}",
                "marker_height_m": c.marker_height_m,
            }
            for c in cars
        ],
        "vision": dataclasses.asdict(settings),
        "lost_s": args.lost,
        "loop": dataclasses.asdict(config),
        "motion": dataclasses.asdict(motion),
        "perception": args.perception,
        "record": {"rate": args.record_rate, "quality": args.record_quality},
    }


async def _drive(args: argparse.Namespace, world: tuple[str, int] | None) -> dict[str, Any]:
    geometry = ArenaGeometry()
    cars = load_fleet(args.fleet)
    settings = VisionSettings(
        geometry,
        tuple(c.marker for c in cars),
        args.calibration,
        {c.marker: c.marker_height_m for c in cars},
    )
    overlay = OverlaySettings(
        None if args.video is None else str(args.video),
        thumbnails=args.web is not None,
        markers={c.car_id: c.marker for c in cars},
    )
    ring = RingSpec(f"udan-ring-{os.getpid()}", args.record_rate) if args.record else None
    # the perception (and web) processes start first and open the camera (bind the page's
    # address) while the model loads
    perception: Perception | None = None
    if args.perception == "process":
        perception = ProcessPerception(args.camera, settings, ring, overlay, args.realtime)
    live = None
    try:
        if args.web is not None:
            config = {
                "rows": geometry.rows,
                "cols": geometry.cols,
                "cars": [c.car_id for c in cars],
                "deadline_ms": DEADLINE_NS / 1e6,
            }
            live = LiveView(*web_address(args.web, args.web_token), args.web_token, config)
        policy, policy_step = load_policy(args.model, geometry)
        transport = open_transport(args.transport, cars, **_transport_options(args))
        if perception is None:
            grabber = FrameGrabber(open_camera(args.camera))
            frames = None if ring is None else FrameRing(ring)
            perception = ThreadPerception(grabber, settings.build(), frames, overlay)
        perception.wait_ready()
        if live is not None:
            print(f"{PROG}: live view at {live.wait_ready()}", flush=True)
    except BaseException:
        if perception is not None:
            perception.close()
        if live is not None:
            live.close()
        raise
    for warning in perception.camera_info.get("warnings", []):
        print(f"{PROG}: warning: camera {args.camera}: {warning}", file=sys.stderr)
    config = LoopConfig(step_timeout_s=args.step_timeout, duration_s=args.duration)
    motion = MotionRules(
        args.settle_mm / 1000,
        math.radians(args.settle_deg),
        geometry=geometry,
        body_m=args.body_mm / 1000,
        cell_time_s=args.cell_time_ms / 1000,
        accel_share=0.0 if args.sim else args.accel_share,
    )
    recorder = None
    if args.record is not None:
        meta = _recording_meta(
            args, policy, policy_step.task, settings, cars, perception, config, motion
        )
        recorder = FlightRecorder(
            args.record, meta, ring=ring, rate=args.record_rate, quality=args.record_quality
        )
    link = CarLink(cars, transport)
    telemetry = Telemetry(
        args.telemetry, live=not args.quiet, tap=None if recorder is None else recorder.telemetry
    )
    fleet = Fleet({c.car_id: c.marker for c in cars}, lost_s=args.lost)
    core = ControlCore(fleet, policy_step, time.monotonic_ns, config.step_timing, motion, recorder)
    shell = EdgeShell(perception, link, core, telemetry, config, live, recorder)
    play = None
    if world is not None:
        play = EpisodePlayer(EpisodePlan(world, args.episodes, args.episode_steps))
    freeze_garbage()
    try:
        await link.start()
    except BaseException:
        perception.close()
        if recorder is not None:
            recorder.close()
        if live is not None:
            live.close()
        raise
    try:
        report = await shell.run(play)
    finally:
        await link.close()
        telemetry.close()
        if live is not None:
            live.close()
        recording = None if recorder is None else recorder.close()
    if recording is not None:
        report["recording"] = recording
    return report


def _start_world(args: argparse.Namespace, fleet: Path, edge: str, camera: str) -> tuple:
    """``python -m udan.hil.world`` as its own process; returns it and its ready line."""
    cmd = [
        sys.executable, "-m", "udan.hil.world",
        "--fleet", str(fleet), "--edge", edge, "--camera-name", camera,
        "--agents", f"1-{args.cars}", "--obstacles", args.obstacles, "--seed", str(args.seed),
        "--cell-time-ms", str(args.cell_time_ms),
    ]  # fmt: skip
    INTERRUPTS.hold()  # a signal inside Popen would leave the world running and unnamed
    proc = None
    try:
        proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, text=True, start_new_session=True, env=parent_watch_env()
        )
        INTERRUPTS.release()
        line = proc.stdout.readline() if proc.stdout else ""
        ready = json.loads(line)
    except json.JSONDecodeError:
        proc.wait(10)
        raise UsageError(f"--sim: the HIL world did not start (exit {proc.returncode})") from None
    except BaseException:  # stopped while the world was starting: it must not outlive us
        INTERRUPTS.release(raise_held=False)
        if proc is not None:
            _stop_world(proc)
        raise
    return proc, ready


def _stop_world(proc: subprocess.Popen) -> str | None:
    """SIGTERM the world and wait for it; returns what it printed last (its summary)."""
    with contextlib.suppress(ProcessLookupError):
        proc.send_signal(signal.SIGTERM)
    try:
        tail, _ = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        tail, _ = proc.communicate()
    return tail


async def _sim(args: argparse.Namespace) -> dict[str, Any]:
    if not 1 <= args.cars <= 5:
        raise UsageError(f"--cars {args.cars}: the arena plays 1-5 cars")
    args.model = args.model or bundled_policy()
    with tempfile.TemporaryDirectory(prefix="udan-sim-") as tmp:
        args.fleet = write_fleet(Path(tmp) / "fleet.toml", args.cars, SIM_MARKER_BASE)
        port = free_udp_port()
        args.listen = f"127.0.0.1:{port}"
        camera = f"udan-sim-{os.getpid()}"
        args.camera = f"virtual://{camera}"
        proc, ready = _start_world(args, args.fleet, args.listen, camera)
        try:
            report = await _drive(args, ("127.0.0.1", ready["control_port"]))
        finally:
            tail = _stop_world(proc)
        world = _last_json(tail)
        if world is not None:
            report["world"] = world
        return report


def _last_json(text: str | None) -> dict[str, Any] | None:
    for line in reversed((text or "").splitlines()):
        with contextlib.suppress(json.JSONDecodeError):
            value = json.loads(line)
            if isinstance(value, dict):
                return value
    return None


def _realtime() -> None:
    try:
        run_realtime()
    except PermissionError:
        raise UsageError("--realtime: not permitted (needs root or CAP_SYS_NICE)") from None


def _event_loop_runner() -> Any:
    """uvloop's runner when installed (its timers wake on time; asyncio's round to 1 ms)."""
    try:
        import uvloop
    except ImportError:
        return asyncio.run
    return uvloop.run


def _quality(text: str) -> int | None:
    """``--record-quality``: a JPEG quality, or None for lossless."""
    if text == "lossless":
        return None
    if not text.isdigit() or not 1 <= int(text) <= 100:
        raise UsageError(f"--record-quality {text}: a JPEG quality 1-100, or lossless")
    return int(text)


def _replay(args: argparse.Namespace) -> tuple[dict[str, Any], int]:
    """``--replay``: the report and the exit code (1 if the recorded model decided otherwise)."""
    from udan.edge.flightlog import read_flight_log
    from udan.edge.replay import check_model, replay_decisions, replay_vision

    if args.sim or args.camera:
        raise UsageError("--replay drives no camera and no car: drop --sim and --camera")
    log = read_flight_log(args.replay)
    model = args.model or Path(log.meta["model"])
    if not model.is_file():
        raise UsageError(f"the recorded model {model} is not here: give --model")
    geometry = ArenaGeometry(**log.meta["vision"]["geometry"])
    _, policy_step = load_policy(model, geometry)
    same = check_model(log, policy_step.task, model)
    decisions = replay_decisions(log, policy_step)
    report: dict[str, Any] = {
        "recording": str(args.replay),
        "model": str(model),
        "recorded_model": log.meta["model"],
        "same_model": same,
        "decisions": decisions,
    }
    whose = "its own model" if same else f"model {model}"
    steps, identical = decisions["steps"], decisions["identical"]
    share = f"{100 * identical / steps:.2f} %" if steps else "-"
    line = f"replayed {steps} decisions of {args.replay} with {whose}: "
    line += f"{identical} as recorded ({share})"
    if identical < steps:
        line += f", {steps - identical} differ ({decisions['commands_differing']} commands)"
    rounds, rounds_same = decisions["recentring_rounds"], decisions["recentring_identical"]
    if rounds:
        line += f"; {rounds_same} of {rounds} re-centring rounds as recorded"
    if decisions["journal_gaps"]:
        line += f" (the recording misses {decisions['journal_gaps']} of the core's inputs)"
    if args.vision:
        vision = report["vision"] = replay_vision(log, args.still)
        lossless = vision["lossless"]
        if lossless["sightings"]:
            line += (
                f"; vision on {lossless['frames']} lossless frames: "
                f"{100 * lossless['same_cell_share']:.2f} % of {lossless['sightings']} sightings "
                f"in the recorded cell, offset p99 {lossless['offset_mm']['p99']} mm"
            )
        else:
            line += "; vision: no lossless frame with a recorded scene"
    report["final"] = line
    return report, int(same and (identical < steps or rounds_same < rounds))


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (2 on bad input)."""
    exit_with_parent()  # if whoever started us asked (udan-hil run): its end is our SIGTERM
    args = _parser().parse_args(argv)
    INTERRUPTS.install()
    code = 0
    try:
        _writable(args.report, "--report")
        _writable(args.telemetry, "--telemetry")
        _writable(args.video, "--video")
        _writable(args.record, "--record")
        args.record_quality = _quality(args.record_quality)
        if not 0 <= args.record_rate <= 1000:
            raise UsageError("--record-rate takes 0-1000 frames a second")
        if args.vision and args.replay is None:
            raise UsageError("--vision goes with --replay")
        if args.still is not None and not args.vision:
            raise UsageError("--still goes with --replay --vision")
        _writable(args.still, "--still")
        if not (0 < args.settle_mm < 1000 * _half_cell_m() and 0 < args.settle_deg < 90):
            raise UsageError(
                f"--settle-mm {args.settle_mm:g} / --settle-deg {args.settle_deg:g}: a tolerance "
                f"must be above 0 and below half a cell ({1000 * _half_cell_m():.0f} mm) "
                "and 90 degrees"
            )
        if not 0 < args.body_mm < 2000 * _half_cell_m():
            raise UsageError(
                f"--body-mm {args.body_mm:g}: a car's body must be above 0 and smaller than a "
                f"cell ({2000 * _half_cell_m():.0f} mm)"
            )
        if not args.cell_time_ms > 0:
            raise UsageError(f"--cell-time-ms {args.cell_time_ms:g}: a move takes some time")
        if not 0 <= args.accel_share < 0.5:
            raise UsageError(f"--accel-share {args.accel_share:g}: a share of a move, 0 to 0.5")
        if args.web is not None:
            web_address(args.web, args.web_token)  # before anything starts
        if args.realtime:
            _realtime()
        if args.replay is not None:
            report, code = _replay(args)
            return _finish(args, report, code)
        if args.sim:
            runner = _sim(args)
        else:
            for name in ("camera", "model", "fleet"):
                if getattr(args, name) is None:
                    raise UsageError(f"--{name} is required (or use --sim)")
            world = host_port(args.world, "--world") if args.world else None
            runner = _drive(args, world)
        report = _event_loop_runner()(runner)
    except (
        UsageError, CameraError, VisionError, FleetFileError, TransportError, TaskError,
        WorldError, WebError, FlightLogError, ReplayError,
    ) as err:  # fmt: skip
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"{PROG}: error: {err.strerror or err}", file=sys.stderr)
        return 2
    except PerceptionError as err:  # every car got its emergency stop in the runtime's finally
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # outside the run: no car is being driven
        print(f"{PROG}: stopped by a signal while starting or closing", file=sys.stderr)
        return 0
    except Exception as err:  # a bug (every car got its emergency stop in the runtime's finally)
        traceback.print_exc()  # what a bug report needs; the last line says it in one
        print(f"{PROG}: fatal: {type(err).__name__}: {err}", file=sys.stderr)
        return 1
    report["scheduler"] = scheduler()
    recording = report.get("recording")
    if recording is not None and (recording["records_dropped"] or "error" in recording):
        print(
            f"{PROG}: warning: the flight recording {recording['file']} is incomplete: "
            f"{recording.get('error') or str(recording['records_dropped']) + ' records dropped'}",
            file=sys.stderr,
        )
    return _finish(args, report, code)


def _finish(args: argparse.Namespace, report: dict[str, Any], code: int) -> int:
    """Write the report, print the final line; ``code``."""
    if args.report is not None:
        args.report.write_text(json.dumps(report, indent=1), encoding="utf-8")
    print(f"{PROG}: {report['final']}" + (f"; report {args.report}" if args.report else ""))
    return code


if __name__ == "__main__":
    sys.exit(main())
