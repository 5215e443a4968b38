"""udan-eval: paper-style tables for the reference policies, and its bad-input contract."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from udan.checkpoint import load_model
from udan.evaluate import CheckpointPolicy, evaluate, main, welch_ci
from udan.policies import OraclePolicy, RandomPolicy

EVAL = [str(Path(sys.executable).with_name("udan-eval"))]


def test_table_has_a_row_per_obstacle_count_and_a_column_per_agent_count(capsys, tmp_path):
    csv_path = tmp_path / "cells.csv"
    code = main(
        [
            "--policy",
            "random",
            "--agents",
            "1-3",
            "--obstacles",
            "0-2",
            "--episodes",
            "3",
            "--csv",
            str(csv_path),
        ]
    )
    assert code == 0
    out = capsys.readouterr().out
    assert "| obstacles \\ agents | 1 | 2 | 3 | mean |" in out
    assert all(f"\n| {m} | " in out for m in range(3))
    assert len(csv_path.read_text().splitlines()) == 1 + 9


def test_same_seed_same_layouts_for_every_policy():
    a = evaluate("arena/find_water", OraclePolicy(), (2, 2), (3, 3), 5, seed=1)
    b = evaluate("arena/find_water", OraclePolicy(), (2, 2), (3, 3), 5, seed=1)
    r = evaluate("arena/find_water", RandomPolicy(), (2, 2), (3, 3), 5, seed=1)
    assert a == b
    assert a[0].agent_score > r[0].agent_score


def test_surround_prints_the_target_table_too(capsys):
    assert (
        main(
            [
                "--policy",
                "oracle",
                "--env",
                "arena/surround",
                "--agents",
                "2",
                "--obstacles",
                "1",
                "--episodes",
                "2",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "target score" in out and "goal score per agent" in out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--agents", "5-1"], "inverted range"),
        (["--agents", "0-2"], "at least 1 agent"),
        (["--agents", "1-12"], "water sources"),
        (["--obstacles", "0-40"], "obstacle zone"),
        (["--env", "arena/nope"], "unknown"),
        (["--policy", "oracle", "--env", "magent/tiger"], "plays arena tasks, not magent/tiger"),
        (["--policy", "chaser", "--env", "magent/queue"], "magent/tiger, not magent/queue"),
        (["--policy", "chaser"], "plays magent/pursuit and magent/tiger, not arena/find_water"),
        (["--policy", "liner", "--env", "magent/tiger"], "plays magent/queue, not magent/tiger"),
        (["--policy", "liner", "--env", "magent/queue", "--obstacles", "3"], "--obstacles 0"),
        (["/nonexistent/checkpoint.pt"], "does not exist"),
        (["--episodes", "0"], "--episodes"),
        (["--csv", "/proc/version/x.csv"], "cannot create folder"),
        (["--env", "magent/tiger", "--prey-alertness", "0.5"], "is for magent/pursuit, not"),
        (["--prey-alertness", "0.5"], "is for magent/pursuit, not arena/find_water"),
        (["--env", "magent/pursuit", "--prey-alertness", "2"], "must lie in [0, 1]"),
        (["--map-size", "30"], "--map-size is for MAgent tasks, not arena/find_water"),
        (["--env", "magent/pursuit", "--map-size", "4"], "map_size must be an int >= 5"),
        (["--env", "magent/pursuit", "--map-size", "6"], "do not fit"),
    ],
)
def test_bad_input_is_one_line_and_exit_code_2(args, message):
    proc = subprocess.run(
        [*EVAL, "--policy", "random", "--episodes", "1", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


def _tiny_checkpoint(tmp_path: Path, **config) -> Path:
    """A checkpoint of a tiny training run (``config``: TrainConfig fields) in ``tmp_path/r``."""
    from udan.train import TrainConfig, train

    small = {"n_envs": 4, "batch_episodes": 4, "hidden": 16, "out": str(tmp_path / "r")}
    return train(TrainConfig(**small, **config), log=lambda *a, **k: None)


def test_a_reference_policy_follows_the_checkpoints_env(tmp_path, capsys):
    path = _tiny_checkpoint(tmp_path, env="arena/surround", steps=200)
    args = [str(path), "--policy", "random", "--agents", "2", "--obstacles", "0", "--episodes", "2"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "arena/surround, random" in out and "arena/surround, udan" in out
    # several policies: each against the first, paired on the same episodes
    assert "arena/surround: each policy against udan (r), paired on the same 2 episodes" in out
    assert "| agents | udan (r) | random | Δ random [95 % CI] | Δ % |" in out
    row = next(line for line in out.splitlines() if line.startswith("| 2 | "))
    base, other, delta = (float(cell.split()[0]) for cell in row.split("|")[2:5])
    assert delta == pytest.approx(other - base, abs=0.011)


def test_map_size_plays_a_magent_checkpoint_on_another_map(tmp_path, capsys):
    """A model trained on one map, played on another (the paper's, with 0) and on its own."""
    path = _tiny_checkpoint(
        tmp_path, env="magent/pursuit", agents="4", map_size=12, max_steps=40, steps=640
    )
    model, _ = load_model(path)
    scores = {}
    for size, options in (("6", {"map_size": 6}), ("0", {}), (None, {"map_size": 12})):
        args = [str(path), "--episodes", "4", "--csv", str(tmp_path / "cells.csv")]
        assert main(args + (["--map-size", size] if size else [])) == 0
        capsys.readouterr()
        played = evaluate(
            "magent/pursuit", CheckpointPolicy(model), (4, 4), (0, 0), 4, 0,
            {"max_steps": 40, **options},
        )  # fmt: skip
        row = (tmp_path / "cells.csv").read_text().splitlines()[1]
        assert f",{played[0].agent_score:.4f}," in row, (size, row)
        scores[size] = played[0].scores.tolist()
    assert len({tuple(each) for each in scores.values()}) == 3  # the three maps play apart


@pytest.mark.parametrize(
    ("a", "b"), [([3.36, 0.75], [9.36, 14.47, 11.0]), ([1.0, 2.0, 4.0], [0.5, 0.7])]
)
def test_welch_interval_is_scipys(a, b):
    from scipy import stats

    difference, half = welch_ci(a, b)
    ci = stats.ttest_ind(a, b, equal_var=False).confidence_interval()
    assert difference == pytest.approx(np.mean(a) - np.mean(b))
    assert (difference - half, difference + half) == pytest.approx((ci.low, ci.high))


def test_welch_interval_of_seeds_that_all_scored_the_same_is_a_point():
    assert welch_ci([-60.0, -60.0], [-60.0, -60.0, -60.0]) == (0.0, 0.0)
