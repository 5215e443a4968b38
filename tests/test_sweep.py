"""udan-sweep: a grid of ordinary runs, its summary and its resumption; on a real local Ray
(slow) the trials as Ray tasks, udan-eval --workers giving the serial numbers, and udan-train
joining a running cluster by its address."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from test_train import one_line_exit_2, quiet, run_cli

from udan.checkpoint import load_checkpoint, load_model
from udan.cluster import ray_map, ray_session
from udan.evaluate import CheckpointPolicy, evaluate
from udan.sweep import main as sweep
from udan.train import TrainConfig, train

SMALL = ["--steps", "400", "--n-envs", "4", "--batch-episodes", "4", "--hidden", "16",
         "--attn-dim", "8", "--mix-dim", "8", "--buffer-episodes", "64"]  # fmt: skip
GRID = ["--algo", "udan,vdn", "--agents", "2,1-3", "--seed", "0-1", "--eval-episodes", "2"]


def trial_files(out: Path) -> dict[str, float]:
    """Each trial checkpoint's modification time."""
    return {p.parent.name: p.stat().st_mtime_ns for p in out.glob("*/checkpoint.pt")}


def test_a_sweep_is_a_folder_of_ordinary_runs_with_a_summary_and_resumes(tmp_path, capsys):
    out = tmp_path / "sweep"
    assert sweep([*SMALL, *GRID, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    names = {
        f"arena-find_water_{algo}_n{agents}_s{seed}"
        for algo in ("udan", "vdn")
        for agents in ("2", "1-3")
        for seed in (0, 1)
    }
    assert set(trial_files(out)) == names and "[8/8]" in printed
    one = out / "arena-find_water_vdn_n1-3_s1"
    ckpt = load_checkpoint(one / "checkpoint.pt")
    assert ckpt["config"]["algo"] == "vdn" and ckpt["config"]["seed"] == 1
    assert ckpt["config"]["agents"] == "1-3" and ckpt["progress"]["steps"] == 400
    with (one / "eval.csv").open() as f:
        cells = list(csv.DictReader(f))
    assert {(int(c["agents"]), int(c["obstacles"])) for c in cells} == {
        (n, m) for n in (1, 2, 3) for m in range(10)
    }
    table = (out / "summary.md").read_text()
    assert table.count("\n| arena/find_water |") == 4 and "| udan | 1-3 | 2 | 400 |" in table
    with (out / "summary.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 8 and {r["status"] for r in rows} == {"done"}
    assert run_cli(one / "checkpoint.pt", "--episodes", 1, tool="udan-eval").returncode == 0

    # the same command: a finished trial is kept, a lost one runs again, a stopped one goes on
    before = trial_files(out)
    (out / "arena-find_water_udan_n2_s0" / "checkpoint.pt").unlink()
    train(TrainConfig(steps=200, **_trial(out, "vdn", "2", 0)), log=quiet)
    assert sweep([*SMALL, *GRID, "--out", str(out)]) == 0
    after = trial_files(out)
    changed = {name for name in after if after[name] != before[name]}
    assert changed == {"arena-find_water_udan_n2_s0", "arena-find_water_vdn_n2_s0"}
    stopped = load_checkpoint(out / "arena-find_water_vdn_n2_s0" / "checkpoint.pt")
    assert stopped["progress"]["steps"] == 400

    one_line_exit_2(
        run_cli(*SMALL, "--algo", "udan", "--out", out, tool="udan-sweep"), "holds another sweep"
    )


def _trial(out: Path, algo: str, agents: str, seed: int) -> dict:
    """A trial's config as the sweep makes it (SMALL's settings), for a run made by hand."""
    small = {"n_envs": 4, "batch_episodes": 4, "hidden": 16, "attn_dim": 8, "mix_dim": 8}
    return {
        **small,
        "buffer_episodes": 64,
        "algo": algo,
        "agents": agents,
        "seed": seed,
        "out": str(out / f"arena-find_water_{algo}_n{agents}_s{seed}"),
    }


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--algo", "udan,qmix", "--agents", "1-5"], "qmix_n1-5_s0: qmix mixes a fixed number"),
        (["--env", "arena/mars"], "unknown env"),
        (["--seed", "3-1"], "inverted range"),
        (["--algo", ","], "--algo: no value"),
        (["--workers", "2", "--address", "127.0.0.1:1"], "no Ray cluster answers there"),
    ],
)
def test_bad_sweep_input(args, fragment, tmp_path):
    one_line_exit_2(run_cli(*SMALL, *args, "--out", tmp_path / "s", tool="udan-sweep"), fragment)


# ------------------------------------------------------------------------- a real local Ray


@pytest.mark.slow
def test_ray_tasks_give_what_one_process_gives(tmp_path):
    """A sweep's trials on Ray train bit for bit as udan-train in this process; udan-eval's
    cells on Ray (ablations included) give the serial numbers."""
    out = tmp_path / "sweep"
    grid = ["--algo", "udan", "--agents", "1-3", "--seed", "0-1", "--eval-episodes", "2"]
    proc = run_cli(*SMALL, *grid, "--out", out, "--workers", 2, tool="udan-sweep", timeout=600)
    assert proc.returncode == 0, proc.stderr
    alone = train(TrainConfig(steps=400, **_trial(tmp_path / "alone", "udan", "1-3", 1)), log=quiet)
    swept = load_checkpoint(out / "arena-find_water_udan_n1-3_s1" / "checkpoint.pt")["weights"]
    here = load_checkpoint(alone)["weights"]
    assert all(torch.equal(here[k], swept[k]) for k in here)

    model, _ = load_model(alone)
    policies = [CheckpointPolicy(model), CheckpointPolicy(model, "messages=shuffle", 3)]
    cells = ("arena/find_water", (1, 3), (0, 2), 4, 5)
    serial = [evaluate(*cells[:1], policy, *cells[1:]) for policy in policies]
    with ray_session(2, ""):
        spread = [evaluate(*cells[:1], policy, *cells[1:], runner=ray_map) for policy in policies]
    for a, b in zip(serial, spread, strict=True):
        assert a == b and all((x.scores == y.scores).all() for x, y in zip(a, b, strict=True))


JOIN = """
import sys
from udan.cluster import ray_session
with ray_session(2, ""):
    import ray
    print(ray.get_runtime_context().gcs_address, flush=True)
    sys.stdin.read()
"""


@pytest.mark.slow
def test_udan_train_joins_a_running_cluster_by_its_address(tmp_path):
    """A cluster another process runs (here a local Ray of two CPUs): --address HOST:PORT."""
    head = subprocess.Popen(
        [sys.executable, "-c", JOIN], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        address = head.stdout.readline().strip()
        assert address, "the cluster did not start"
        out = tmp_path / "w"
        proc = run_cli(*SMALL, "--steps", 800, "--address", address, "--out", out, timeout=300)
        assert proc.returncode == 0, proc.stderr
        ckpt = load_checkpoint(out / "checkpoint.pt")
        assert ckpt["progress"]["steps"] == 800 and ckpt["workers"]["started"] == 2  # its CPUs
        assert sum(ckpt["workers"]["rollouts"].values()) * 4 == ckpt["progress"]["episodes"]
    finally:
        head.communicate("", timeout=120)
    assert head.returncode == 0
