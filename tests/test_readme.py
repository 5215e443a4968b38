"""The README's examples, run: every command of its code blocks at tiny sizes, in an empty folder,
so the page cannot drift from the code. Sizes are shrunk by replacing the values of the flags the
README gives (a renamed or removed flag still fails) and adding size flags; the commands that
need hardware (a camera device, real-time priority) have their flags parsed by the command's own
parser instead. A command no rule here knows fails the test: a new example needs a rule."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from udan.edge.cli import _parser as edge_parser

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")
BIN = Path(sys.executable).parent

# For each command, flags set to tiny values (the README's value replaced, or the flag added).
SHRINK: dict[str, dict[str, str]] = {
    "udan-train": {"--steps": "200"},
    "udan-eval": {"--agents": "1-2", "--obstacles": "0-1", "--episodes": "1"},
    "udan-edge": {"--duration": "3"},
    "udan-hil run": {"--cars": "2", "--obstacles": "0", "--episodes": "1"},
    "udan-firmware-mock": {"--base-port": "0"},
}
EXTRA: dict[str, list[str]] = {
    "udan-train": ["--n-envs", "4", "--batch-episodes", "4", "--hidden", "16"],
    "udan-export": ["--sizes", "1,3", "--steps", "2"],
    "udan-edge": ["--quiet"],
    "udan-hil run": ["--episode-steps", "5"],
}
# Flags whose README value is replaced where given, never added: a fixed port may be taken.
REPLACE: dict[str, str] = {"--web": "127.0.0.1:0"}
TRAINING = ("udan-train", "udan-eval", "udan-export")
HARDWARE_FLAGS = ("--camera", "--realtime")


def code_blocks(lang: str) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```", README, flags=re.M | re.S)


def commands() -> list[list[str]]:
    """Each command line of the shell blocks, continuation lines joined and comments dropped;
    ``...`` (the flags of the line before) is left out."""
    out = []
    for block in code_blocks("sh"):
        for line in block.replace("\\\n", " ").splitlines():
            words = [w for w in shlex.split(line, comments=True) if w != "..."]
            if words:
                out.append(words)
    return out


def name(words: list[str]) -> str:
    return " ".join(words[:2]) if words[:2] == ["udan-hil", "run"] else words[0]


def shrunk(words: list[str]) -> list[str]:
    """``words`` with SHRINK's flags set (replaced where the README gives them) and EXTRA's
    flags added."""
    key, out = name(words), list(words)
    for flag, value in SHRINK.get(key, {}).items():
        if flag in out:
            out[out.index(flag) + 1] = value
        else:
            out += [flag, value]
    for flag, value in REPLACE.items():
        if flag in out:
            out[out.index(flag) + 1] = value
    return [str(BIN / out[0]), *out[1:], *EXTRA.get(key, [])]


def run(words: list[str], cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(shrunk(words), cwd=cwd, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{' '.join(words)}\n{proc.stderr[-2000:]}"
    return proc


def pick(rule) -> list[list[str]]:
    return [words for words in commands() if rule(words)]


def is_hardware(words: list[str]) -> bool:
    return words[0] == "udan-edge" and any(f in words for f in HARDWARE_FLAGS)


def is_sim(words: list[str]) -> bool:
    return words[0] == "udan-edge" and "--sim" in words


def is_replay(words: list[str]) -> bool:
    return words[0] == "udan-edge" and "--replay" in words


def test_every_readme_command_has_a_rule() -> None:
    known = {
        "make",
        *TRAINING,
        "udan-firmware-mock",
        "udan-hil run",
    }
    found = commands()
    assert len(found) >= 11
    for words in found:
        assert name(words) in known or is_hardware(words) or is_sim(words) or is_replay(words), (
            words
        )


@pytest.mark.parametrize("words", pick(lambda w: w[0] == "make"), ids=" ".join)
def test_make_targets_exist(words: list[str]) -> None:
    proc = subprocess.run(["make", "-n", *words[1:]], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_training_commands_in_order(tmp_path: Path) -> None:
    """Train (both), evaluate, export, as the README chains them through runs/ and out/
    (about 20 s at these sizes)."""
    steps = pick(lambda w: w[0] in TRAINING)
    assert [w[0] for w in steps] == ["udan-train", "udan-train", "udan-eval", "udan-export"]
    for words in steps:
        run(words, tmp_path)
    assert (tmp_path / "runs/fw/checkpoint.pt").is_file()
    assert (tmp_path / "runs/fw_qmix/checkpoint.pt").is_file()
    assert {p.suffix for p in (tmp_path / "out/eval").iterdir()} >= {".csv", ".png"}
    assert (tmp_path / "runs/fw/policy.onnx").is_file()  # where the README says it goes


def test_fleet_file_and_mock_firmware(tmp_path: Path) -> None:
    """The README's fleet.toml, read by the edge's reader and served by the mock cars."""
    from udan.fleetfile import load_fleet

    (toml,) = code_blocks("toml")
    (tmp_path / "fleet.toml").write_text(toml, encoding="utf-8")
    fleet = load_fleet(tmp_path / "fleet.toml")
    (words,) = pick(lambda w: w[0] == "udan-firmware-mock")
    proc = subprocess.Popen(
        shrunk(words), cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        ready = json.loads(proc.stdout.readline() or "{}")
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert ready.get("ready"), err
    assert len(ready["cars"]) == len(fleet) == int(words[words.index("--cars") + 1])


@pytest.mark.parametrize("words", pick(is_hardware), ids=" ".join)
def test_hardware_commands_parse(words: list[str]) -> None:
    args = edge_parser().parse_args(words[1:])
    for flag, value in zip(words[1:], [*words[2:], None], strict=True):
        if flag.startswith("--") and value is not None and not value.startswith("--"):
            assert str(getattr(args, flag[2:].replace("-", "_"))) == value, flag
        elif flag.startswith("--"):
            assert getattr(args, flag[2:].replace("-", "_")) is True, flag


@pytest.mark.parametrize("words", pick(is_sim), ids=" ".join)
def test_edge_sim(words: list[str], tmp_path: Path) -> None:
    proc = run(words, tmp_path)
    assert "commands on time" in proc.stdout + proc.stderr


def test_edge_replay(tmp_path: Path) -> None:
    """The recorded --sim run, then its replay, in the same folder."""
    (recorded,) = pick(lambda w: is_sim(w) and "--record" in w)
    (replay,) = pick(is_replay)
    run(recorded, tmp_path)
    proc = run(replay, tmp_path)
    assert "as recorded (100.00 %)" in proc.stdout


def test_hil_run(tmp_path: Path) -> None:
    (words,) = pick(lambda w: name(w) == "udan-hil run")
    run(words, tmp_path)
    report = words[words.index("--report") + 1]
    summary = json.loads((tmp_path / report / "summary.json").read_text())
    assert summary["headline"]["episodes"] >= 1


def test_python_example() -> None:
    """The Python block, with ``actions`` (which it leaves to the reader) all "wait"."""
    (code,) = code_blocks("python")
    scope = {"actions": np.full((4096, 5), 4)}
    exec(code, scope)
    assert scope["obs"].shape == (4096, 5, 155)  # as its comment says
