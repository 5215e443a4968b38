"""The flight recorder as a user runs it: ``udan-edge --record`` beside the HIL world (real
processes, the recorder one of them), the file read back with the ``mcap`` reader, ``--replay``
with the recorded model and another, ``--replay --vision``, and bad input."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from test_edge_cli import _world_and_edge

from udan.edge import flightlog as fl
from udan.edge.transport import free_udp_port
from udan.fleetfile import load_fleet, write_fleet
from udan.models import bundled_policy

UDAN_EDGE = str(Path(sys.executable).with_name("udan-edge"))
MODELS = bundled_policy().parents[1]


@dataclass
class Recorded:
    folder: Path
    fleet: Path
    mcap: Path
    report: dict[str, Any]


def _edge(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([UDAN_EDGE, *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Recorded:
    """The HIL world and ``udan-edge --record`` on a fleet file of our own (its keys known),
    for 15 s; the cars move as a lab's do (moves end off their cells' centres: re-centring
    rounds, the guard watching)."""
    folder = tmp_path_factory.mktemp("recorded")
    fleet = write_fleet(folder / "fleet.toml", 2)
    edge_port, camera = free_udp_port(), f"udan-test-{time.monotonic_ns()}"
    world = subprocess.Popen(
        [
            sys.executable, "-m", "udan.hil.world", "--fleet", str(fleet),
            "--edge", f"127.0.0.1:{edge_port}", "--camera-name", camera, "--agents", "1-2",
            "--obstacles", "0-3", "--cell-time-ms", "60", "--motion-error", "lab",
        ],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        control = json.loads(world.stdout.readline())["control_port"]
        done = _edge(
            "--camera", f"virtual://{camera}", "--model", str(bundled_policy()),
            "--fleet", str(fleet), "--listen", f"127.0.0.1:{edge_port}",
            "--world", f"127.0.0.1:{control}", "--episode-steps", "20", "--duration", "15",
            "--record", str(folder / "run.mcap"), "--report", str(folder / "edge.json"),
            "--quiet",
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
    finally:
        world.send_signal(signal.SIGTERM)
        world.wait(30)
    report = json.loads((folder / "edge.json").read_text())
    return Recorded(folder, fleet, folder / "run.mcap", report)


def test_the_recorder_kept_up_and_wrote_every_decided_frame(recorded: Recorded) -> None:
    steps = recorded.report["counts"]["steps"]
    rec = recorded.report["recording"]
    assert steps > 20 and rec["recorder"] == "exit code 0"
    assert rec["records_dropped"] == 0 and rec["journal_gaps"] == 0
    # a decided frame is lost only if the recorder fell a whole ring behind (a loaded machine)
    assert rec["frames_lossless"] + rec["frames_missed"] == steps
    assert rec["frames_lossless"] >= 0.8 * steps
    assert rec["frames_lossy"] > 0 and rec["bytes"] == recorded.mcap.stat().st_size


def test_the_file_reads_back_every_channel_with_its_schema(recorded: Recorded) -> None:
    with recorded.mcap.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert reader.get_header().profile == fl.PROFILE
        channels = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
        assert channels.keys() == {*fl.SCHEMAS, *fl.IMAGE_TOPICS}
        assert channels[fl.LOSSLESS_TOPIC].name == "foxglove.RawImage"
        assert channels[fl.JPEG_TOPIC].name == "foxglove.CompressedImage"
        counts: dict[str, int] = {}
        for _, channel, message in reader.iter_messages():
            topic = channel.topic
            counts[topic] = counts.get(topic, 0) + 1
            schema = channels[topic]
            if topic in fl.IMAGE_TOPICS:
                assert schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
                continue
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            body = json.loads(message.data)
            required = json.loads(schema.data)["required"]
            assert set(required) <= body.keys(), (topic, body)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert counts[fl.DECISION_TOPIC] == recorded.report["counts"]["steps"]
    assert counts[fl.SCENE_TOPIC] == recorded.report["counts"]["frames"]
    assert counts[fl.LOSSLESS_TOPIC] == recorded.report["recording"]["frames_lossless"]
    run = {k: json.loads(v) for k, v in meta[fl.META].items()}
    assert run["task"] == "find_water" and len(run["model_sha256"]) == 64
    assert [c["id"] for c in run["fleet"]] == [1, 2]
    assert run["camera"]["mode"]["width"] == 1920 and run["code_version"]
    assert json.loads(meta["udan-recorder"]["journal_gaps"]) == 0


def _every_byte_of(path: Path) -> list[bytes]:
    """The file as it is, and everything the mcap reader finds in it (decompressed)."""
    out = [path.read_bytes()]
    with path.open("rb") as stream:
        reader = make_reader(stream)
        out += [message.data for _, _, message in reader.iter_messages()]
        out += [json.dumps(m.metadata).encode() for m in reader.iter_metadata()]
        out += [a.data for a in reader.iter_attachments()]
    return out


def test_no_key_of_the_fleet_file_is_anywhere_in_the_recording(recorded: Recorded) -> None:
    keys = [car.key for car in load_fleet(recorded.fleet)]
    assert len(keys) == 2 and all(len(k) == 32 for k in keys)
    forms = [form for k in keys for form in (k, k.hex().encode(), k.hex().upper().encode())]
    for blob in _every_byte_of(recorded.mcap):
        assert not any(form in blob for form in forms)


def test_a_replay_with_the_recorded_model_decides_every_step_the_same(
    recorded: Recorded, tmp_path: Path
) -> None:
    done = _edge("--replay", str(recorded.mcap), "--report", str(tmp_path / "replay.json"))
    assert done.returncode == 0, done.stderr
    report = json.loads((tmp_path / "replay.json").read_text())
    decisions = report["decisions"]
    assert report["same_model"] is True
    assert decisions["steps"] == recorded.report["counts"]["steps"]
    assert decisions["identical"] == decisions["steps"] and decisions["differences"] == []
    assert "as recorded (100.00 %)" in done.stdout
    # the re-centring rounds of cars that ended their moves off centre, too
    assert decisions["recentring_rounds"] == recorded.report["counts"]["recentre_rounds"] > 0
    assert decisions["recentring_identical"] == decisions["recentring_rounds"]


def test_a_replay_with_another_model_shows_what_it_would_have_done(
    recorded: Recorded, tmp_path: Path
) -> None:
    qmix = MODELS / "baselines" / "find_water_qmix" / "policy.onnx"
    done = _edge("--replay", str(recorded.mcap), "--model", str(qmix),
                 "--report", str(tmp_path / "replay.json"))  # fmt: skip
    assert done.returncode == 0, done.stderr
    decisions = json.loads((tmp_path / "replay.json").read_text())["decisions"]
    assert decisions["steps"] == recorded.report["counts"]["steps"]
    assert decisions["differing"] > 0 and f"with model {qmix}" in done.stdout


def test_the_vision_again_on_the_recorded_frames_agrees(recorded: Recorded, tmp_path: Path) -> None:
    done = _edge("--replay", str(recorded.mcap), "--vision", "--still", str(tmp_path / "s.png"),
                 "--report", str(tmp_path / "replay.json"))  # fmt: skip
    assert done.returncode == 0, done.stderr
    still = cv2.imread(str(tmp_path / "s.png"))
    assert still.shape[1] == 960 and still.std() > 10  # a frame, drawn on
    vision = json.loads((tmp_path / "replay.json").read_text())["vision"]
    lossless = vision["lossless"]
    assert lossless["frames"] > 0.8 * recorded.report["counts"]["steps"]
    assert lossless["sightings"] >= lossless["frames"]
    assert lossless["same_cell_share"] == 1.0 and lossless["missing"] == 0
    assert lossless["offset_mm"]["p99"] < 10.0


def test_bad_recordings_and_replays_are_one_line_and_exit_2(
    recorded: Recorded, tmp_path: Path
) -> None:
    data = recorded.mcap.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    foreign = tmp_path / "foreign.mcap"
    with foreign.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2", library="a robot")
        writer.finish()
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not a recording at all" * 100)
    surround = MODELS / "surround" / "policy.onnx"
    hidden = MODELS / "hidden_goal" / "policy.onnx"
    cases = [
        (["--replay", str(cut)], "cut.mcap"),
        (["--replay", str(foreign)], "is an MCAP file but not a udan-edge recording"),
        (["--replay", str(junk)], "not an MCAP file"),
        (["--replay", str(tmp_path / "none.mcap")], "none.mcap: no such file"),
        (["--replay", str(recorded.mcap), "--model", str(surround)], "plays surround"),
        (["--replay", str(recorded.mcap), "--model", str(hidden)], "not an arena task the cars"),
        (["--replay", str(recorded.mcap), "--sim"], "--replay drives no camera and no car"),
        (["--sim", "--vision"], "--vision goes with --replay"),
        (["--replay", str(recorded.mcap), "--still", "s.png"], "--still goes with --replay"),
        (["--sim", "--record-quality", "0"], "--record-quality 0: a JPEG quality 1-100"),
        (["--sim", "--record", str(tmp_path / "no" / "run.mcap")], "does not exist"),
    ]
    for args, says in cases:
        done = _edge(*args, timeout=120)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2, (args, done.stderr)
        assert len(lines) == 1 and lines[0].startswith("udan-edge: error: "), (args, lines)
        assert says in lines[0], (args, lines)


def test_an_edge_killed_mid_run_leaves_a_recording_that_replays(tmp_path: Path) -> None:
    """The recorder finishes the file when the edge's end of its socket closes, however the
    edge ended: SIGKILLed mid-run, its recording still reads back and replays exactly."""
    fleet = write_fleet(tmp_path / "fleet.toml", 2)
    mcap, telemetry = tmp_path / "run.mcap", tmp_path / "telemetry.jsonl"
    extra = ["--record", str(mcap), "--telemetry", str(telemetry)]
    with _world_and_edge(tmp_path, fleet, extra) as (_, edge, _):
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and (
            not telemetry.exists() or telemetry.read_text().count('"kind":"step"') < 10
        ):
            time.sleep(0.2)
        edge.kill()
        edge.wait(30)
    deadline = time.monotonic() + 60
    while True:  # the recorder writes what it holds and the file's end, then exits
        try:
            log = fl.read_flight_log(mcap)
            break
        except fl.FlightLogError:
            assert time.monotonic() < deadline, "the recording was never finished"
            time.sleep(0.5)
    assert sum(e.call == "decide" for e in log.entries) >= 10
    done = _edge("--replay", str(mcap), "--report", str(tmp_path / "replay.json"))
    assert done.returncode == 0, done.stderr
    decisions = json.loads((tmp_path / "replay.json").read_text())["decisions"]
    assert decisions["identical"] == decisions["steps"] >= 10


@pytest.mark.slow
def test_a_minute_of_sim_recorded_replays_exactly_and_the_vision_agrees(tmp_path: Path) -> None:
    """The issue's own check: 60 s of ``udan-edge --sim --record``, replayed: every decision the
    same, and the vision again on the lossless frames puts every car in its recorded cell."""
    done = _edge("--sim", "--duration", "60", "--record", str(tmp_path / "run.mcap"),
                 "--report", str(tmp_path / "edge.json"), "--quiet", timeout=240)  # fmt: skip
    assert done.returncode == 0, done.stderr
    steps = json.loads((tmp_path / "edge.json").read_text())["counts"]["steps"]
    done = _edge("--replay", str(tmp_path / "run.mcap"), "--vision",
                 "--report", str(tmp_path / "replay.json"), timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr
    report = json.loads((tmp_path / "replay.json").read_text())
    assert steps > 100 and report["decisions"]["identical"] == steps
    assert report["vision"]["lossless"]["same_cell_share"] == 1.0
