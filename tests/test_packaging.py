"""One import namespace: the top-level folders edge/, export/, firmware_mock/, hil/ and models/
are ``udan.edge`` ... ``udan.models`` through the build configuration, in this (editable) install
as in a wheel (``make wheel-check`` proves the wheel). Here: the mapping holds in-process, in
subprocesses started from an empty folder (no checkout on ``sys.path``), for ``python -m``, the
entry points and ``python -P bench/*.py``, and the configuration covers every package folder."""

from __future__ import annotations

import ast
import importlib
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from udan.models import DEFAULT_POLICY, bundled_policy

ROOT = Path(__file__).resolve().parents[1]
MAPPED = ("edge", "export", "firmware_mock", "hil", "models")
BIN = Path(sys.executable).parent
CONFIG = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("folder", MAPPED)
def test_each_folder_is_a_udan_subpackage(folder: str) -> None:
    module = importlib.import_module(f"udan.{folder}")
    assert Path(module.__file__).parent == ROOT / folder


def test_from_an_empty_folder_only_udan_is_importable(tmp_path: Path) -> None:
    """No checkout on sys.path: what resolves is the install's mapping, and the old top-level
    names (taken by other distributions) are gone."""
    probe = (
        "import importlib, importlib.util, json\n"
        f"mods = {{m: importlib.import_module('udan.' + m).__file__ for m in {MAPPED!r}}}\n"
        f"old = [m for m in {MAPPED!r} if importlib.util.find_spec(m)]\n"
        "from udan.models import bundled_policy\n"
        "print(json.dumps([mods, old, str(bundled_policy())]))\n"
    )
    proc = run([sys.executable, "-c", probe], tmp_path)
    assert proc.returncode == 0, proc.stderr
    mods, old, policy = json.loads(proc.stdout)
    assert {m: Path(f).parent for m, f in mods.items()} == {m: ROOT / m for m in MAPPED}
    assert old == []
    assert Path(policy) == ROOT / "models" / DEFAULT_POLICY / "policy.onnx"


@pytest.mark.parametrize(
    "cmd",
    [
        ["-m", "udan.hil.world", "--help"],
        ["-m", "udan.firmware_mock.cli", "--help"],
        ["-m", "udan.edge.cli", "--help"],
    ],
)
def test_python_m_from_an_empty_folder(cmd: list[str], tmp_path: Path) -> None:
    proc = run([sys.executable, *cmd], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("usage:")


@pytest.mark.parametrize(
    "cmd",
    [
        ["udan-edge", "--help"],
        ["udan-hil", "run", "--help"],
        ["udan-export", "--help"],
        ["udan-firmware-mock", "--help"],
        ["udan-eval", "--help"],
        ["udan-sweep", "--help"],
        ["udan-paper", "--help"],
    ],
)
def test_entry_points_from_an_empty_folder(cmd: list[str], tmp_path: Path) -> None:
    proc = run([str(BIN / cmd[0]), *cmd[1:]], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("usage:")


def test_hil_defaults_to_the_bundled_policy() -> None:
    from udan.hil.harness import _parser

    args = _parser().parse_args(["run", "--duration", "1"])
    assert args.model == bundled_policy() and args.model.is_file()


def test_bundled_policy_names_what_is_missing() -> None:
    assert bundled_policy("surround").is_file()
    with pytest.raises(FileNotFoundError, match="no bundled policy 'nope'"):
        bundled_policy("nope")


@pytest.mark.parametrize("script", sorted((ROOT / "bench").glob("*.py")), ids=lambda p: p.name)
def test_bench_imports_resolve_under_python_P(script: Path) -> None:
    """`make bench` runs `python -P bench/X.py` (the script's folder not on sys.path): every
    project import of the script resolves through the install, without running the bench."""
    imports = [
        ast.unparse(node)
        for node in ast.walk(ast.parse(script.read_text()))
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("udan")
    ]
    assert imports, f"{script.name} imports nothing of udan"
    code = "\n".join([*imports, "import udan.edge", "print(udan.edge.__file__)"])
    proc = run([sys.executable, "-P", "-c", code], ROOT)
    assert proc.returncode == 0, proc.stderr
    assert Path(proc.stdout.strip()).parent == ROOT / "edge"


def test_configuration_lists_every_package_folder() -> None:
    """A package folder the configuration forgets would be missing from the wheel only, which
    the editable install would never show; so each folder with Python files is listed here."""
    mapping = {"udan": "udan", **{f"udan.{m}": m for m in MAPPED}}
    assert CONFIG["package-dir"] == {k: v for k, v in mapping.items() if k != "udan"}
    expected = set()
    for package, folder in mapping.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            expected.add(".".join((package, *rel)))
    shipped = {f"udan.models.{p.parent.name}" for p in (ROOT / "models").glob("*/policy.onnx")}
    assert set(CONFIG["packages"]) == expected | shipped
    assert CONFIG["package-data"] == {
        **{p: ["policy.onnx"] for p in shipped},
        "udan.edge": ["static/*"],  # the live page's files, read with importlib.resources
    }
    from udan.edge.web import _static

    for path in (ROOT / "edge" / "static").iterdir():
        assert _static(path.name) == path.read_bytes()
