"""udan-paper at a tiny size: the paper's numbers beside ours, ours equal to udan-eval's, "not
trained yet" wherever no model is committed, the same file twice, a MAgent model's row, and the
committed docs/results.md made from the committed models."""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np
import pytest
from test_train import TINY, one_line_exit_2, quiet, run_cli

from udan.checkpoint import load_model
from udan.evaluate import CheckpointPolicy, evaluate
from udan.paper import NOT_TRAINED, TABLE_II, TABLE_V_AGENT, TABLE_V_GOAL, TABLE_VI, main

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"


def _models(tmp_path: Path, *folders: str) -> Path:
    """A models folder holding only ``folders`` of the committed ones (linked, not copied)."""
    models = tmp_path / "models"
    for folder in folders:
        (models / folder).parent.mkdir(parents=True, exist_ok=True)
        (models / folder).symlink_to(MODELS / folder, target_is_directory=True)
    return models


#: The queue VDN baseline's folder (three training seeds in the MAgent test's models).
QUEUE_VDN = "baselines/magent_queue_vdn"
#: The pursuit IQL baseline's try on a map of its own, the VDN baseline on the paper's, and the
#: labels of UDAN's try and IQL's.
PURSUIT_IQL_TRY = "baselines/magent_pursuit_iql/map30"
PURSUIT_VDN = "baselines/magent_pursuit_vdn"
TRY_LABELS = (
    "UDAN, 30×30 map, slow ε, sheep curriculum (a deviation)",
    "IQL, 30×30 map, slow ε, sheep curriculum (a deviation)",
)


def _row(text: str, title: str, first: str) -> list[float]:
    """The numbers of the row starting with ``| first |`` in the table under ``**title**``."""
    table = text[text.index(f"**{title}**") :]
    row = next(line for line in table.splitlines() if line.startswith(f"| {first} |"))
    return [float(v) for v in re.findall(r"-?\d+\.\d+", row.removeprefix(f"| {first} |"))]


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> tuple[Path, str]:
    tmp = tmp_path_factory.mktemp("paper")
    models = _models(tmp, "surround", "hidden_goal")
    out = tmp / "docs" / "results.md"
    assert main(["--models", str(models), "--out", str(out), "--episodes", "3"]) == 0
    return out, out.read_text()


def test_table_v_is_udan_eval_beside_the_paper(written):
    _, text = written
    model, _ = load_model(MODELS / "surround" / "checkpoint.pt")
    cells = evaluate("arena/surround", CheckpointPolicy(model), (1, 5), (0, 0), 3, seed=0)
    row = _row(text, "Table V: average agent score", "0")
    assert row[0::2] == pytest.approx([c.agent_score for c in cells], abs=0.006)
    assert row[1::2] == pytest.approx(TABLE_V_AGENT[0], abs=0.0006)  # N = 5: no paper column
    goal = _row(text, "Table V: goal score per agent", "0")
    assert goal[0::2] == pytest.approx([c.goal_per_agent for c in cells], abs=0.006)
    assert goal[1::2] == pytest.approx(TABLE_V_GOAL[0], abs=0.0006)
    means = _row(text, "Table V: average agent score", "mean")
    paper = np.mean(list(TABLE_V_AGENT.values()), axis=0)
    assert means[1::2] == pytest.approx(paper, abs=0.006)
    assert "the paper has no N = 5 column" in text


def test_what_is_not_committed_is_not_trained_yet_never_a_number(written):
    _, text = written
    fig7 = text[text.index("**Fig. 7: average agent score by N**") :]
    for label in ("QMIX", "VDN", "COMA"):
        row = next(line for line in fig7.splitlines() if line.startswith(f"| {label} |"))
        assert row.count(NOT_TRAINED) == 5 and not re.search(r"\d\.\d", row)
    table_vi = text[text.index("## Table VI") : text.index("## The positive control")]
    assert f"UDAN: {NOT_TRAINED}" in table_vi
    assert f"{TABLE_VI[14][0]:.2f}" not in table_vi  # nothing of ours to set beside it
    magent = text[text.index("## Table II") :]
    rows = [line for line in magent.splitlines() if line.startswith("| pursuit |")]
    assert len(rows) == 13 and all(NOT_TRAINED in row for row in rows)  # 5 learners, 8 tries
    assert f"{TABLE_II['qmix']['15']:g} (trained on 15)" in magent
    assert "Fig. 5 (learning curves): not trained yet." in magent


def test_the_control_and_the_figures_are_written(written):
    out, text = written
    control = text[text.index("## The positive control") : text.index("## Table II")]
    assert "| proven no-message bound | 14.45 |" in control
    assert "UDAN with shuffled messages" in control
    assert "| UDAN, no messages |" in control
    figures = out.parent / "results"
    assert (figures / "fig7_surround.png").stat().st_size > 10_000
    assert "![Fig. 7](results/fig7_surround.png)" in text


@pytest.mark.slow
def test_the_same_models_give_the_same_file(written, tmp_path):
    out, text = written
    models = out.parents[1] / "models"
    again = tmp_path / "docs" / "results.md"
    assert main(["--models", str(models), "--out", str(again), "--episodes", "3"]) == 0
    assert again.read_text() == text


def test_a_committed_magent_model_gets_its_row_and_curves(tmp_path):
    from udan.train import TrainConfig, train

    models = _models(tmp_path, "hidden_goal")
    queue = {"agents": "1-3", "obstacles": "0", "map_size": 8, "max_steps": 12}
    pursuit = {"agents": "2-3", "obstacles": "0", "map_size": 12, "max_steps": 12}
    tiny = {**TINY, "leader_explore": 0.3}
    for env, folder, algo, seeds, steps, options in (
        ("magent/queue", "magent_queue", "udan", 2, 480, queue),
        ("magent/queue", QUEUE_VDN, "vdn", 3, 480, queue),
        ("magent/pursuit", "magent_pursuit", "udan", 1, 288, pursuit),
        ("magent/pursuit", "magent_pursuit/map30", "udan", 2, 288, {**pursuit, "map_size": 8}),
        ("magent/pursuit", PURSUIT_IQL_TRY, "iql", 2, 288, {**pursuit, "map_size": 8}),
        ("magent/pursuit", PURSUIT_VDN, "vdn", 2, 288, pursuit),  # on the paper's map
    ):
        for seed in range(seeds):  # further training seeds in seed<k>/ folders of their own
            train(
                TrainConfig(
                    env=env,
                    algo=algo,
                    steps=steps,
                    seed=seed,
                    out=str(models / folder / (f"seed{seed}" if seed else "")),
                    **options,
                    **tiny,
                ),
                log=quiet,
            )
    out = tmp_path / "results.md"
    assert main(["--models", str(models), "--out", str(out), "--episodes", "2"]) == 0
    text = out.read_text()
    row = next(line for line in text.splitlines() if line.startswith("| queue | UDAN |"))
    assert "| 1-3 | 1-3 |" in row and NOT_TRAINED not in row
    assert "curves only (Fig. 5)" in row
    assert "| magent_queue |" in text and (tmp_path / "results" / "fig5_curves.png").is_file()
    for scenario, tested in (("pursuit", "2-3"), ("queue", "1-3")):
        scripted = next(
            line for line in text.splitlines() if line.startswith(f"| {scenario} | scripted")
        )  # on the UDAN's sizes and task options
        assert re.search(rf"\| {tested} \| -?\d+\.\d\d \[", scripted), scripted
    assert not any(line.startswith("| tiger | scripted") for line in text.splitlines())
    for scenario, trained in (
        ("queue", "1-3"),
        ("pursuit", "2-3"),
        ("pursuit (`magent_pursuit/map30`)", "2-3"),
    ):
        shuffle = text.index(f"**{scenario}: UDAN with shuffled messages, paired")
        assert f"| {trained} pooled |" in text[shuffle:].split("\n\n", 2)[1]
    _a_try_on_its_own_map_is_played_there(text, models)
    _the_seeds_table_is_each_seed_played_alone(text, models)
    _a_try_is_set_against_the_baselines_on_its_task(text, models)
    _the_queue_walk_is_each_policy_s(text, models)


def _the_queue_walk_is_each_policy_s(text: str, models: Path) -> None:
    """Queue's walk table gives each policy's cells left to the nearest line, as udan-eval
    measures them on the same episodes (10 per N)."""
    from udan.policies import LinerPolicy

    def walk(policy) -> str:
        options = {"map_size": 8, "max_steps": 12}
        cells = evaluate("magent/queue", policy, (1, 3), (0, 0), 10, 0, options)
        return f"{np.mean([c.line_walk for c in cells]):.2f} |"

    table = text[text.index("**queue: how near the fleet came to a line**") :].split("\n\n")[1]
    rows = dict(line.rsplit(" | ", 1) for line in table.splitlines()[2:])
    model, _ = load_model(models / QUEUE_VDN / "checkpoint.pt")
    assert rows["| VDN"] == walk(CheckpointPolicy(model))
    assert rows["| scripted liner (no learning, no messages)"] == walk(LinerPolicy(0))


def _a_try_on_its_own_map_is_played_there(text: str, models: Path) -> None:
    """A try trained on another map than the scenario's UDAN is played on its own map, beside the
    scripted chaser on that map, and not set against the paper's number there; then on the
    paper's map, where it is."""
    from udan.policies import ChaserPolicy

    def pooled(policy, map_size: int = 8) -> str:
        options = {"map_size": map_size, "max_steps": 12}
        cells = evaluate("magent/pursuit", policy, (2, 3), (0, 0), 10, 0, options)
        return f"| {np.concatenate([c.scores for c in cells]).mean():.2f} ["

    lines = text.splitlines()
    row = next(line for line in lines if line.startswith("| pursuit | UDAN, 30×30 map"))
    assert "| 2-3 | 2-3 |" in row and "| — (the paper's task: 12×12 map, 12 steps) |" in row
    model, _ = load_model(models / "magent_pursuit/map30/checkpoint.pt")
    assert pooled(CheckpointPolicy(model)) in row
    there = lines[lines.index(row) + 1]
    assert there.startswith(
        "| pursuit | UDAN, 30×30 map, slow ε, sheep curriculum (a deviation), played on the "
        "paper's 12×12 map, 12 steps | 2-3 | 2-3 | "
    )
    assert pooled(CheckpointPolicy(model), 12) in there and there.endswith("71 (trained on 8-20) |")
    chaser = "| pursuit | scripted chaser (no learning, no messages), on the 8×8 map, 12 steps"
    scripted = next(line for line in lines if line.startswith(chaser))
    assert scripted.startswith(chaser + " | — | 2-3 | " + pooled(ChaserPolicy(0))[2:])


def _the_seeds_table_is_each_seed_played_alone(text: str, models: Path) -> None:
    """Each seed's score is udan-eval's pooled score of that checkpoint alone (10 episodes per N,
    udan-paper's default), their CI is Student's t over the seeds, UDAN − VDN is Welch's t on
    the two learners' seeds, and the shuffle row is each UDAN seed's paired loss."""
    from scipy import stats

    def played(folder: str, ablate: str | None = None) -> float:
        model, _ = load_model(models / folder / "checkpoint.pt")
        policy = CheckpointPolicy(model, ablate, 0) if ablate else CheckpointPolicy(model)
        options = {"map_size": 8, "max_steps": 12}
        cells = evaluate("magent/queue", policy, (1, 3), (0, 0), 10, 0, options)
        return np.concatenate([c.scores for c in cells]).mean()

    table = "queue: across training seeds"
    udan_folders = ("magent_queue", "magent_queue/seed1")
    scores = {
        "UDAN": [played(folder) for folder in udan_folders],
        "VDN": [played(f"{QUEUE_VDN}{f'/seed{seed}' if seed else ''}") for seed in range(3)],
    }
    for label, each in scores.items():
        n, mean = len(each), np.mean(each)
        half = stats.t.ppf(0.975, n - 1) * np.std(each, ddof=1) / np.sqrt(n)
        assert _row(text, table, label) == pytest.approx(
            [*each, mean, mean - half, mean + half], abs=0.006
        )
    welch = stats.ttest_ind(scores["UDAN"], scores["VDN"], equal_var=False).confidence_interval()
    difference = np.mean(scores["UDAN"]) - np.mean(scores["VDN"])
    assert _row(text, table, "UDAN − VDN (Welch's t)") == pytest.approx(
        [difference, welch.low, welch.high], abs=0.006
    )
    costs = [
        played(folder, "messages=shuffle") - full
        for folder, full in zip(udan_folders, scores["UDAN"], strict=True)
    ]
    row = next(line for line in text.splitlines() if line.startswith("| UDAN, Δ messages=shuffle"))
    assert "| 0, 1 |" in row and f"{costs[0]:+.2f}, {costs[1]:+.2f}" in row
    assert "| magent_queue/seed1 |" in text  # its learning curve, named by its folder


def _a_try_is_set_against_the_baselines_on_its_task(text: str, models: Path) -> None:
    """A UDAN try with seeds is set against a baseline's try with seeds on their own map, and,
    played on the paper's map, against both that try and the baseline trained there (Welch's t
    over the seeds, each seed played on that map); never a seed played on one map against one
    played on another; and the try's shuffle rows are its own, on each map."""
    from scipy import stats

    def played(folder: str, map_size: int) -> float:
        model, _ = load_model(models / folder / "checkpoint.pt")
        options = {"map_size": map_size, "max_steps": 12}
        cells = evaluate("magent/pursuit", CheckpointPolicy(model), (2, 3), (0, 0), 10, 0, options)
        return np.concatenate([c.scores for c in cells]).mean()

    def seeds(folder: str, map_size: int) -> list[float]:
        return [played(f"{folder}{suffix}", map_size) for suffix in ("", "/seed1")]

    table = "pursuit: across training seeds"
    udan, iql = TRY_LABELS
    there = ", played on the paper's 12×12 map, 12 steps"
    pairs = (
        (udan, iql, seeds("magent_pursuit/map30", 8), seeds(PURSUIT_IQL_TRY, 8)),
        (udan + there, iql + there, seeds("magent_pursuit/map30", 12), seeds(PURSUIT_IQL_TRY, 12)),
        (udan + there, "VDN", seeds("magent_pursuit/map30", 12), seeds(PURSUIT_VDN, 12)),
    )
    for ours, baseline, mine, theirs in pairs:
        assert _row(text, table, ours)[:2] == pytest.approx(mine, abs=0.006)
        assert _row(text, table, baseline)[:2] == pytest.approx(theirs, abs=0.006)
        welch = stats.ttest_ind(mine, theirs, equal_var=False).confidence_interval()
        assert _row(text, table, f"{ours} − {baseline} (Welch's t)") == pytest.approx(
            [np.mean(mine) - np.mean(theirs), welch.low, welch.high], abs=0.006
        )
    rows = text[text.index(f"**{table}**") :].split("\n\n", 2)[1].splitlines()
    assert len([row for row in rows if "(Welch's t)" in row]) == len(pairs)
    assert not any(row.startswith("| UDAN −") for row in rows)  # the main UDAN has one seed
    for ours in (udan, udan + there):
        assert any(
            row.startswith(f"| {ours}, Δ messages=shuffle (paired) | 0, 1 |") for row in rows
        )


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--episodes", "1"], "must be >= 2"),
        (["--models", "{tmp}/none"], "no checkpoint.pt under"),
        (["--out", "{tmp}"], "is a folder, not a file"),
        (["--out", "/proc/version/results.md"], "cannot create folder"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, args, fragment):
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    one_line_exit_2(run_cli(*args, tool="udan-paper"), fragment)


def test_docs_results_is_made_from_the_committed_models():
    """Retraining a model means running ``make paper``: the file lists what it was made from."""
    text = (ROOT / "docs" / "results.md").read_text()
    listed = dict(re.findall(r"\| `models/(\S+)` \(\w+\) \| `([0-9a-f]{16})` \|", text))
    for folder, sha in listed.items():
        path = MODELS / folder / "checkpoint.pt"
        assert hashlib.sha256(path.read_bytes()).hexdigest()[:16] == sha, folder
    committed = {str(p.parent.relative_to(MODELS)) for p in MODELS.rglob("checkpoint.pt")}
    assert set(listed) == committed
