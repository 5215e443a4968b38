"""bench/tools/compare.py: two checkouts' figures interleaved, the ratio with its interval."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).parents[1] / "bench" / "tools" / "compare.py"
spec = importlib.util.spec_from_file_location("compare", SCRIPT)
compare = importlib.util.module_from_spec(spec)
spec.loader.exec_module(compare)


def test_flatten_keeps_numbers_by_dotted_path() -> None:
    value = {"a": {"p99_ms": 1.5, "ok": True, "name": "x"}, "n": 3, "l": [1, {"k": 2.0}]}
    assert compare.flatten(value) == {"a.p99_ms": 1.5, "n": 3.0, "l.0": 1.0, "l.1.k": 2.0}


def test_ratio_ci_covers_the_true_ratio_and_excludes_one_when_it_differs() -> None:
    same = compare.ratio_ci([1.0, 1.1, 0.9, 1.05], [1.02, 0.98, 1.08, 0.95])
    assert same["ci95"][0] < 1 < same["ci95"][1]
    slower = compare.ratio_ci([1.0, 1.02, 0.99, 1.01], [1.5, 1.52, 1.49, 1.51])
    assert 1.45 < slower["ci95"][0] < slower["ratio"] < slower["ci95"][1] < 1.55


def _checkout(folder: Path, value: float) -> Path:
    """A stand-in checkout: its .venv/bin/python prints a figure (and the file it was asked for)."""
    bin_dir = folder / ".venv" / "bin"
    bin_dir.mkdir(parents=True)
    script = bin_dir / "figure"
    script.write_text(
        f"#!{sys.executable}\nimport json, sys, pathlib\n"
        f"out = {{'p99_ms': {value}, 'nested': {{'n': 3}}}}\n"
        "if len(sys.argv) > 1: pathlib.Path(sys.argv[1], 'r.json').write_text(json.dumps(out))\n"
        "print('noise'); print(json.dumps(out))\n"
    )
    script.chmod(0o755)
    return folder


@pytest.mark.parametrize("read", [None, "r.json"])
def test_the_cli_runs_both_checkouts_and_reports_each_field(tmp_path: Path, read) -> None:
    a, b = _checkout(tmp_path / "a", 2.0), _checkout(tmp_path / "b", 3.0)
    cmd = "{bin}/figure" + (" {out}" if read else "")
    extra = ["--read", read] if read else []
    done = subprocess.run(
        [sys.executable, str(SCRIPT), str(a), str(b), "--cmd", cmd, "--rounds", "2", *extra],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    fields = json.loads(done.stdout)["fields"]
    assert fields["p99_ms"]["ratio"] == 1.5 and fields["nested.n"]["ratio"] == 1.0


def test_a_failing_command_is_one_line_and_exit_2(tmp_path: Path) -> None:
    a, b = _checkout(tmp_path / "a", 2.0), _checkout(tmp_path / "b", 3.0)
    done = subprocess.run(
        [sys.executable, str(SCRIPT), str(a), str(b), "--cmd", "false"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
