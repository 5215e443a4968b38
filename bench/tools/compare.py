"""Two checkouts, one measurement, interleaved: is B's figure A's within noise?

How DESIGN.md reads a change's "unchanged" or "≤ 1.05×": the same command run alternately in two
checkouts (A B A B ..., so a slow stretch of a shared machine falls on both), each run's JSON
flattened to its numeric fields, and for each field the ratio B/A of the means with a 95 %
confidence interval (t-interval on the difference of the runs' log values, Welch). Prints one
JSON object; ``--fields`` picks the fields to report (default: every one both sides printed).

The command is a template run by the shell in each checkout, with ``{bin}`` the checkout's
``.venv/bin`` and ``{out}`` a fresh folder per run; its figures are read from its standard output
(the last line that is a JSON object) or, with ``--read``, from a file under ``{out}``::

    python -P bench/tools/compare.py /work/before /work/main --rounds 5 \\
        --cmd '{bin}/python -P bench/dispatch.py' --fields no_faults.commands_on_time_share
    python -P bench/tools/compare.py /work/before /work/main --rounds 2 \\
        --cmd '{bin}/udan-hil run --cars 5 --duration 120 --report {out}' --read summary.json
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from scipy import stats


def flatten(value: Any, prefix: str = "") -> dict[str, float]:
    """Every number in a JSON value, keyed by its dotted path (lists by index)."""
    if isinstance(value, bool):
        return {}
    if isinstance(value, int | float):
        return {prefix: float(value)} if math.isfinite(value) else {}
    items = (
        value.items()
        if isinstance(value, dict)
        else enumerate(value)
        if isinstance(value, list)
        else ()
    )
    out: dict[str, float] = {}
    for key, inner in items:
        out.update(flatten(inner, f"{prefix}.{key}" if prefix else str(key)))
    return out


def ratio_ci(a: list[float], b: list[float]) -> dict[str, float | None]:
    """Ratio of means B/A and a 95 % interval from the log values (None where undefined)."""
    mean_a, mean_b = sum(a) / len(a), sum(b) / len(b)
    result: dict[str, float | None] = {
        "a": round(mean_a, 6),
        "b": round(mean_b, 6),
        "ratio": round(mean_b / mean_a, 4) if mean_a else None,
        "ci95": None,
    }
    if len(a) < 2 or len(b) < 2 or min(a + b) <= 0:
        return result
    la, lb = [math.log(x) for x in a], [math.log(x) for x in b]
    va, vb = stats.tvar(la) / len(la), stats.tvar(lb) / len(lb)
    diff = sum(lb) / len(lb) - sum(la) / len(la)
    if va + vb == 0:
        result["ci95"] = [round(math.exp(diff), 4)] * 2
        return result
    dof = (va + vb) ** 2 / (va**2 / (len(la) - 1) + vb**2 / (len(lb) - 1))
    half = stats.t.ppf(0.975, dof) * math.sqrt(va + vb)
    result["ci95"] = [round(math.exp(diff - half), 4), round(math.exp(diff + half), 4)]
    return result


def run_once(checkout: Path, cmd: str, read: str | None) -> dict[str, float]:
    """The command in ``checkout``; its figures, flattened."""
    with tempfile.TemporaryDirectory(prefix="compare-") as out:
        text = cmd.format(bin=checkout / ".venv" / "bin", out=out)
        done = subprocess.run(text, shell=True, cwd=checkout, capture_output=True, text=True)
        if done.returncode != 0:
            last = (done.stderr.strip().splitlines() or [""])[-1]
            raise RuntimeError(f"{checkout}: {text!r} exited {done.returncode} {last}".rstrip())
        if read is not None:
            return flatten(json.loads((Path(out) / read).read_text()))
        for line in reversed(done.stdout.splitlines()):
            if line.startswith("{"):
                return flatten(json.loads(line))
    raise RuntimeError(f"{checkout}: {text!r} printed no JSON object")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("a", type=Path, help="the reference checkout (with its own .venv)")
    p.add_argument("b", type=Path, help="the checkout under test")
    p.add_argument("--cmd", required=True, help="command template ({bin}, {out})")
    p.add_argument("--read", help="read the figures from this file under {out}")
    p.add_argument("--rounds", type=int, default=5, help="runs of each, interleaved")
    p.add_argument("--fields", nargs="*", help="dotted fields to report (default: all)")
    args = p.parse_args(argv)
    runs: dict[str, list[dict[str, float]]] = {"a": [], "b": []}
    try:
        for i in range(args.rounds):
            for side in ("a", "b") if i % 2 == 0 else ("b", "a"):
                runs[side].append(run_once(getattr(args, side), args.cmd, args.read))
    except RuntimeError as err:
        print(f"compare: {err}", file=sys.stderr)
        return 2
    common = set.intersection(*(set(r) for side in runs.values() for r in side))
    fields = [f for f in (args.fields or sorted(common)) if f in common]
    report = {
        "a": str(args.a),
        "b": str(args.b),
        "cmd": args.cmd,
        "rounds": args.rounds,
        "fields": {
            f: ratio_ci([r[f] for r in runs["a"]], [r[f] for r in runs["b"]]) for f in fields
        },
    }
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
