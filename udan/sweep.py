"""``udan-sweep``: a grid of ``udan-train`` runs — algorithms x training N x seeds x tasks.

Every ``udan-train`` flag is a ``udan-sweep`` flag; ``--algo``, ``--agents``, ``--seed`` and
``--env`` take comma-separated lists (seeds also ranges: ``0-4``), and the grid is every
combination. Each trial is an ordinary run folder under ``--out`` (``udan-eval`` reads its
checkpoint), trained in one process exactly as ``udan-train`` would train it, then evaluated on
the agent counts it was trained on (``--eval-episodes`` per cell, seed 0: every trial meets the
same layouts). With ``--workers N`` the trials run as Ray tasks, N at a time (a local Ray, or
the cluster at ``--address``); without, one after the other here. A summary table closes the
sweep (``summary.md``, ``summary.csv``). Running the same command again resumes it: finished
trials are kept, unfinished ones go on from their last checkpoint, missing ones start.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import itertools
import json
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from udan.checkpoint import CheckpointError, load_checkpoint, load_model
from udan.cluster import ScaleError
from udan.envs import EnvConfigError
from udan.envs.errors import parse_range
from udan.evaluate import CheckpointPolicy, evaluate, write_csv
from udan.paths import FolderError, ensure_folder
from udan.train import RESUMABLE_FIELDS, TrainConfig, build, env_options, field_docs, train

#: The flags that take lists; their combinations are the trials.
GRID = ("env", "algo", "agents", "seed")
#: udan-train flags a sweep sets itself: where each trial writes, and how trials are spread.
OWN = ("out", "workers", "address", "broadcast_every")
#: Columns of summary.csv, one row per trial.
COLUMNS = ("trial", "env", "algo", "agents", "seed", "steps", "return", "score", "seconds")


def parse_grid(flag: str, text: str) -> list[str]:
    """A grid flag's comma-separated values; seeds may be ranges (``0-4``)."""
    values = [v.strip() for v in text.split(",") if v.strip()]
    if not values:
        raise EnvConfigError(f"--{flag}: no value in {text!r}")
    if flag != "seed":
        return values
    seeds = []
    for value in values:
        lo, hi = parse_range(value, "--seed")
        seeds += [str(s) for s in range(lo, hi + 1)]
    return seeds


def trial_name(cfg: TrainConfig) -> str:
    """The trial's folder name, e.g. ``arena-find_water_udan_n1-5_s0``."""
    return f"{cfg.env.replace('/', '-')}_{cfg.algo}_n{cfg.agents}_s{cfg.seed}"


def trials(base: dict, grid: dict[str, list[str]], out: Path) -> list[TrainConfig]:
    """Every combination of the grid on top of ``base`` (TrainConfig fields), each with its
    folder under ``out``; refuses a combination ``udan-train`` would refuse."""
    configs = []
    for values in itertools.product(*(grid[flag] for flag in GRID)):
        cfg = TrainConfig(**{**base, **dict(zip(GRID, values, strict=True))})
        cfg = dataclasses.replace(cfg, seed=int(cfg.seed), out=str(out / trial_name(cfg)))
        try:
            build(dataclasses.replace(cfg, n_envs=1))
        except EnvConfigError as err:
            raise EnvConfigError(f"trial {trial_name(cfg)}: {err}") from None
        configs.append(cfg)
    return configs


def run_trial(cfg: TrainConfig, eval_episodes: int) -> dict:
    """Train (or resume, or keep when finished) and evaluate one trial in its run folder; its
    summary row (``status`` done, or failed with the one-line reason)."""
    out = Path(cfg.out)
    path = out / "checkpoint.pt"
    row = {"trial": out.name, "env": cfg.env, "algo": cfg.algo, "agents": cfg.agents}
    row["seed"] = cfg.seed
    try:
        resume = path.exists()
        if not resume or load_checkpoint(path)["progress"]["steps"] < cfg.steps:
            (out / "eval.csv").unlink(missing_ok=True)  # of a checkpoint about to change
            train(cfg, resume=resume, log=_quiet)
        if eval_episodes and not (out / "eval.csv").exists():
            evaluate_trial(path, eval_episodes)
        progress = load_checkpoint(path)["progress"]
    except (EnvConfigError, CheckpointError) as err:
        return {**row, "status": f"failed: {err}"}
    score = ""
    if (out / "eval.csv").exists():
        with (out / "eval.csv").open() as f:
            score = f"{np.mean([float(r['agent_score']) for r in csv.DictReader(f)]):.3f}"
    with (out / "progress.csv").open() as f:
        last = list(csv.DictReader(f))[-1]
    return {
        **row,
        "steps": progress["steps"],
        "return": last["return"],
        "score": score,
        "seconds": round(progress["seconds"], 1),
        "status": "done",
    }


def evaluate_trial(path: Path, episodes: int) -> None:
    """``eval.csv`` beside the checkpoint at ``path``: every agent count it was trained on (and
    0-9 obstacles on an arena task), ``episodes`` per cell, seed 0."""
    model, ckpt = load_model(path)
    cfg = ckpt["config"]
    obstacles = (0, 9) if cfg["env"].startswith("arena/") else (0, 0)
    agents = parse_range(cfg["agents"], "--agents")
    policy = CheckpointPolicy(model)
    cells = evaluate(cfg["env"], policy, agents, obstacles, episodes, 0, env_options(cfg))
    write_csv(cells, path.parent / "eval.csv")


def _quiet(*args: object, **kwargs: object) -> None:
    """A trial's training says nothing: its progress.csv and TensorBoard events say it all."""


def serial_trials(configs: list[TrainConfig], eval_episodes: int) -> Iterator[dict]:
    """The trials here, one after the other."""
    for cfg in configs:
        yield run_trial(cfg, eval_episodes)


def ray_trials(configs: list[TrainConfig], eval_episodes: int) -> Iterator[dict]:
    """The trials as Ray tasks of one CPU (Ray runs as many at once as it has CPUs), in the
    order they finish. A task whose process dies is run again: it resumes from its trial's
    last checkpoint."""
    from udan.cluster import import_ray

    ray = import_ray()
    remote = ray.remote(num_cpus=1, max_retries=1)(run_trial)
    pending = [remote.remote(cfg, eval_episodes) for cfg in configs]
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        yield ray.get(ready[0])


def summary(rows: list[dict], title: str) -> str:
    """Markdown: one line per (env, algo, agents) with its trials' training return and
    evaluation score, mean ± standard deviation over seeds, and the core-hours spent."""
    lines = [
        f"**{title}**",
        "",
        "| env | algo | agents | seeds | steps | training return | score | core-hours |",
        "|---|---|---|---|---|---|---|---|",
    ]
    done = [r for r in rows if r["status"] == "done"]
    for key in sorted({(r["env"], r["algo"], r["agents"]) for r in done}):
        group = [r for r in done if (r["env"], r["algo"], r["agents"]) == key]
        returns = np.array([float(r["return"]) for r in group])
        scores = np.array([float(r["score"]) for r in group if r["score"] != ""])
        hours = sum(r["seconds"] for r in group) / 3600
        lines.append(
            f"| {' | '.join(map(str, key))} | {len(group)} | {group[0]['steps']:,} "
            f"| {_spread(returns)} | {_spread(scores)} | {hours:.2f} |"
        )
    for r in rows:
        if r["status"] != "done":
            lines.append(f"\n{r['trial']}: {r['status']}")
    return "\n".join(lines)


def _spread(values: np.ndarray) -> str:
    if values.size == 0:
        return "-"
    if values.size == 1:
        return f"{values[0]:.2f}"
    return f"{values.mean():.2f} ± {values.std(ddof=1):.2f}"


def check_same_sweep(out: Path, plan: dict) -> None:
    """``out`` holds no sweep, or this one (``steps`` and ``checkpoint_every`` may change)."""
    path = out / "sweep.json"
    if not path.is_file():
        return
    before = json.loads(path.read_text())
    differ = sorted(
        key
        for key in {*before["base"], *plan["base"]}
        if key not in RESUMABLE_FIELDS and before["base"].get(key) != plan["base"].get(key)
    )
    differ += [key for key in ("grid", "eval_episodes") if before[key] != plan[key]]
    if differ:
        raise EnvConfigError(
            f"{out} holds another sweep (it differs in {', '.join(differ)}); use another --out"
        )


def parser() -> argparse.ArgumentParser:
    docs = field_docs(TrainConfig)
    parse = argparse.ArgumentParser(prog="udan-sweep", description=__doc__.splitlines()[0])
    for f in dataclasses.fields(TrainConfig):
        if f.name in OWN:
            continue
        kind = float if f.type in ("float", float) else int if f.type in ("int", int) else str
        listed = f.name in GRID
        parse.add_argument(
            f"--{f.name.replace('_', '-')}",
            dest=f.name,
            type=str if listed else kind,
            default=str(f.default) if listed else f.default,
            help=("comma-separated list: " if listed else "")
            + f"{docs.get(f.name, '')} (default: %(default)s)",
        )
    parse.add_argument("--out", default="sweeps/default", help="sweep folder, one run per trial")
    parse.add_argument(
        "--workers",
        type=int,
        default=0,
        help="trials at once, as Ray tasks on a local Ray (0: one after the other, here)",
    )
    parse.add_argument(
        "--address", default="", help="run the trials on this Ray cluster: ray://HOST:PORT, auto"
    )
    parse.add_argument(
        "--eval-episodes",
        type=int,
        default=20,
        help="episodes per cell of each trial's evaluation (0: none)",
    )
    return parse


def main(argv: list[str] | None = None) -> int:
    args = vars(parser().parse_args(argv))
    out, workers, address = Path(args.pop("out")), args.pop("workers"), args.pop("address")
    eval_episodes = args.pop("eval_episodes")
    try:
        if workers < 0 or eval_episodes < 0:
            raise EnvConfigError("--workers and --eval-episodes must be >= 0")
        grid = {flag: parse_grid(flag, args.pop(flag)) for flag in GRID}
        base = {**args, "workers": 0, "address": ""}
        configs = trials(base, grid, out)
        plan = {"base": base, "grid": grid, "eval_episodes": eval_episodes}
        check_same_sweep(out, plan)
        ensure_folder(out, "--out")
        (out / "sweep.json").write_text(json.dumps(plan, indent=1))
        print(f"udan-sweep: {len(configs)} trials in {out}", flush=True)
        started, rows = time.perf_counter(), []
        if workers or address:
            from udan.cluster import ray_session

            with ray_session(workers, address):
                for row in ray_trials(configs, eval_episodes):
                    rows.append(_report(row, len(rows) + 1, len(configs)))
        else:
            for row in serial_trials(configs, eval_episodes):
                rows.append(_report(row, len(rows) + 1, len(configs)))
    except (EnvConfigError, CheckpointError, FolderError, ScaleError) as err:
        print(f"udan-sweep: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\nudan-sweep: interrupted; the same command resumes the sweep", file=sys.stderr)
        return 130
    rows.sort(key=lambda r: r["trial"])
    with (out / "summary.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, [*COLUMNS, "status"], extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    minutes = (time.perf_counter() - started) / 60
    table = summary(rows, f"{out}: {len(rows)} trials, {minutes:.1f} min of wall time")
    (out / "summary.md").write_text(table + "\n")
    print(table)
    return 0 if all(r["status"] == "done" for r in rows) else 1


def _report(row: dict, count: int, total: int) -> dict:
    """One line per finished trial."""
    said = f"score {row['score']}" if row.get("score") else f"return {row.get('return', '-')}"
    state = row["status"] if row["status"] != "done" else f"done, {said}"
    print(f"[{count}/{total}] {row['trial']}: {state}", flush=True)
    return row


if __name__ == "__main__":
    sys.exit(main())
