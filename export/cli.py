"""``udan-export``: checkpoint -> verified ONNX policy; ``verify`` and ``bench`` on a policy.

    udan-export CHECKPOINT [-o OUT]          export, verify, write (default: policy.onnx beside
                                             the checkpoint; OUT may be a file or a folder)
    udan-export verify POLICY CHECKPOINT     checker, symbolic axes, ORT vs torch at many N
    udan-export bench POLICY [--checkpoint CHECKPOINT]   latency JSON, ORT vs torch eager

Exit codes: 0 good, 1 verification failed (nothing written on export), 2 bad input (one line
on stderr: missing or unreadable file, not a checkpoint or policy, missing output folder).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from google.protobuf.message import DecodeError
from onnxruntime.capi.onnxruntime_pybind11_state import Fail, InvalidArgument, InvalidProtobuf

from udan.envs.observe import ObsSpec
from udan.export.metadata import MetadataError, build_metadata, check_metadata
from udan.paths import FolderError, ensure_folder

if TYPE_CHECKING:
    import onnx

# The torch side (udan.checkpoint, udan.export.graph, .verify, .bench) and onnx are imported by
# the commands that use them: a mistyped path is reported in a second, not after torch has loaded,
# and `--help` works on an install without the train extra.
TRAIN_EXTRA = ("torch", "onnx")


class InputError(ValueError):
    """Bad input the user can fix; reported in one line with exit code 2."""


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _sizes(text: str) -> tuple[int, ...]:
    try:
        sizes = tuple(int(s) for s in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of counts: {text}") from None
    if not sizes or min(sizes) < 1:
        raise argparse.ArgumentTypeError(f"agent counts must be >= 1: {text}")
    return sizes


def output_path(checkpoint: Path, out: str | None) -> Path:
    """Where the policy goes: ``-o`` as a file, or ``policy.onnx`` inside ``-o`` (a folder) or
    beside the checkpoint."""
    if out is None:
        return checkpoint.parent / "policy.onnx"
    path = Path(out)
    if path.is_dir():
        return path / "policy.onnx"
    try:
        ensure_folder(path.parent, "-o")
    except FolderError as err:
        raise InputError(str(err)) from None
    return path


def load_policy(path: Path) -> tuple[onnx.ModelProto, dict[str, str]]:
    """The ONNX model and its metadata, after :func:`check_metadata` (a foreign file is told
    which metadata it lacks)."""
    if not path.is_file():
        raise InputError(f"policy {path} does not exist")
    import onnx

    try:
        model = onnx.load(str(path))
    except (DecodeError, OSError, ValueError) as err:
        raise InputError(f"{path} is not an ONNX file ({type(err).__name__})") from None
    meta = {p.key: p.value for p in model.metadata_props}
    try:
        check_metadata(meta)
    except MetadataError as err:
        raise InputError(f"{path}: {err}") from None
    return model, meta


def load_model(path: Path):
    """(model, checkpoint dict); torch is imported here, on one thread: the networks are small
    and on a busy machine more threads are far slower."""
    import torch

    from udan.checkpoint import CheckpointError
    from udan.checkpoint import load_model as load

    torch.set_num_threads(1)
    try:
        return load(path)
    except CheckpointError as err:
        raise InputError(str(err)) from None


def _print_report(lines: list[str], ok: bool, sha_ok: bool | None = None) -> None:
    print("\n".join(lines[:-1]))
    if sha_ok is not None:
        print("source checkpoint sha256: " + ("matches" if sha_ok else "DIFFERS"))
    print("verdict: " + ("PASS" if ok else "FAIL"))


def cmd_export(args: argparse.Namespace) -> int:
    checkpoint = Path(args.checkpoint)
    out = output_path(checkpoint, args.output)
    model, ckpt = load_model(checkpoint)
    from udan.export.graph import build_graph
    from udan.export.verify import SIZES, verify

    meta = build_metadata(ckpt, dataclasses.asdict(model.spec), sha256(checkpoint))
    onnx_model = build_graph(model, meta)
    report = verify(onnx_model, model, args.sizes or SIZES, args.steps)
    _print_report(report.lines(), report.ok)
    if not report.ok:
        print(f"verification failed: {out} not written", file=sys.stderr)
        return 1
    import onnx

    onnx.save(onnx_model, str(out))
    print(f"wrote {out} ({out.stat().st_size / 1e3:.1f} kB, {ckpt['algo']}, {ckpt['env']})")
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    policy, checkpoint = Path(args.policy), Path(args.checkpoint)
    onnx_model, meta = load_policy(policy)
    model, ckpt = load_model(checkpoint)
    from udan.export.verify import SIZES, verify

    obs = ckpt["obs_spec"]
    try:
        check_metadata(meta, ObsSpec(obs["height"], obs["width"], obs["view"], obs["version"]))
    except MetadataError as err:
        raise InputError(f"{policy}: {err}") from None
    sha_ok = meta["checkpoint_sha256"] == sha256(checkpoint)
    spec = model.spec
    differ = [
        f"{key} {meta[key]} vs {value}"
        for key, value in (("algo", spec.algo), ("hidden", spec.hidden), ("obs_dim", spec.obs_dim))
        if meta[key] != str(value)
    ]
    if differ:  # parity cannot even run: say why instead
        lines = [f"{policy} is not a model of {checkpoint}: {', '.join(differ)}", ""]
        _print_report(lines, False, sha_ok)
        return 1
    report = verify(onnx_model, model, args.sizes or SIZES, args.steps)
    _print_report(report.lines(), report.ok and sha_ok, sha_ok)
    return 0 if report.ok and sha_ok else 1


def cmd_bench(args: argparse.Namespace) -> int:
    policy = Path(args.policy)
    _, meta = load_policy(policy)
    checkpoint = Path(args.checkpoint) if args.checkpoint else policy.parent / "checkpoint.pt"
    if not checkpoint.is_file() or sha256(checkpoint) != meta["checkpoint_sha256"]:
        raise InputError(
            f"bench compares with torch: give the checkpoint {policy} was exported from "
            f"(--checkpoint; {checkpoint} is missing or another file)"
        )
    model, _ = load_model(checkpoint)
    from udan.export.bench import SIZES, bench

    print(json.dumps(bench(policy, model, args.sizes or SIZES, args.repeats), indent=1))
    return 0


def parser(command: str) -> argparse.ArgumentParser:
    prog = "udan-export" if command == "export" else f"udan-export {command}"
    p = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    if command == "export":
        p.add_argument("checkpoint", help="checkpoint.pt from udan-train")
        p.add_argument("-o", "--output", help="policy file, or folder for policy.onnx")
    elif command == "verify":
        p.add_argument("policy", help="exported policy (.onnx)")
        p.add_argument("checkpoint", help="the checkpoint it was exported from")
    else:
        p.add_argument("policy", help="exported policy (.onnx)")
        p.add_argument("--checkpoint", help="its checkpoint (default: checkpoint.pt beside it)")
        p.add_argument("--sizes", type=_sizes, help="agent counts, a,b,c (default: 1,5,...,1000)")
        p.add_argument("--repeats", type=int, default=200, help="timed calls per size")
    if command != "bench":
        p.add_argument("--sizes", type=_sizes, help="agent counts, a,b,c (default: 1,2,...,1000)")
        p.add_argument("--steps", type=int, default=4, help="consecutive steps per size")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    command = argv[0] if argv and argv[0] in ("verify", "bench") else "export"
    args = parser(command).parse_args(argv[1:] if command != "export" else argv)
    run = {"export": cmd_export, "verify": cmd_verify, "bench": cmd_bench}[command]
    try:
        return run(args)
    except (InputError, Fail, InvalidArgument, InvalidProtobuf) as err:
        print(f"udan-export: error: {str(err).strip().splitlines()[0]}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as err:
        if err.name not in TRAIN_EXTRA:
            raise
        print(
            f"udan-export: error: {command} needs {err.name}: pip install 'udan-edge[train]'",
            file=sys.stderr,
        )
        return 2


if __name__ == "__main__":
    sys.exit(main())
