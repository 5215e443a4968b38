"""udan-train end to end at tiny sizes: learning, exact resume, checkpoints, bad input."""

import csv
import dataclasses
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from udan.checkpoint import CheckpointError, load_checkpoint, load_model
from udan.evaluate import CheckpointPolicy, evaluate
from udan.learner import ALGOS, leader_targets
from udan.policies import OraclePolicy
from udan.train import EpisodeReplay, TrainConfig, field_docs, train

BIN = Path(sys.executable).parent
TINY = {
    "n_envs": 4,
    "batch_episodes": 4,
    "updates_per_rollout": 2,
    "hidden": 16,
    "attn_dim": 8,
    "mix_dim": 8,
    "buffer_episodes": 64,
}


def quiet(*args, **kwargs):
    pass


@pytest.mark.parametrize("algo", [a for a in ALGOS if a != "coma"])
def test_every_algo_trains_and_its_checkpoint_acts(tmp_path, algo):
    agents = "3" if algo == "qmix" else "1-4"
    cfg = TrainConfig(algo=algo, agents=agents, steps=800, out=str(tmp_path / algo), **TINY)
    path = train(cfg, log=quiet)
    model, ckpt = load_model(path)
    assert ckpt["algo"] == algo and ckpt["env"] == "arena/find_water"
    assert ckpt["obs_spec"]["version"] == 1 and ckpt["progress"]["steps"] == 800
    assert ckpt["config"]["agents"] == agents
    assert (tmp_path / algo / "progress.csv").read_text().count("\n") >= 4
    res = evaluate("arena/find_water", CheckpointPolicy(model), (1, 4), (0, 0), 2, seed=0)
    assert len(res) == 4  # evaluated at every N, also those QMIX never saw


def test_save_load_gives_identical_actions(tmp_path):
    path = train(TrainConfig(steps=400, out=str(tmp_path / "r"), **TINY), log=quiet)
    a, _ = load_model(path)
    b, _ = load_model(path)
    r1 = evaluate("arena/find_water", CheckpointPolicy(a), (3, 3), (2, 2), 4, seed=3)
    r2 = evaluate("arena/find_water", CheckpointPolicy(b), (3, 3), (2, 2), 4, seed=3)
    assert r1 == r2


@pytest.mark.parametrize(
    "algo_options", [{"algo": "udan"}, {"algo": "coma", "agents": "3"}], ids=["udan", "coma"]
)
def test_an_interrupted_run_resumes_exactly(tmp_path, algo_options):
    """Both training loops (replay-based and on-policy) continue bit-identically after Ctrl-C."""

    def config(out):
        return TrainConfig(
            steps=1600, out=str(tmp_path / out), checkpoint_every=800, **{**TINY, **algo_options}
        )

    straight = train(config("a"), log=quiet)

    def interrupt_after_first_checkpoint(*args, **kwargs):
        if args and "steps 1,000" in args[0]:  # the rollout after the 800-step checkpoint
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(config("b"), log=interrupt_after_first_checkpoint)
    assert load_checkpoint(tmp_path / "b" / "checkpoint.pt")["progress"]["steps"] == 800
    with pytest.raises(CheckpointError, match="config differs"):
        train(dataclasses.replace(config("b"), lr=0.1), resume=True, log=quiet)
    # checkpointing more often changes when state is saved, never what is learnt
    resumed = train(dataclasses.replace(config("b"), checkpoint_every=400), resume=True, log=quiet)
    a, b = load_checkpoint(straight), load_checkpoint(resumed)
    for key in ("weights", "target_weights", "critic_weights", "critic_target_weights"):
        if a.get(key) is not None:
            assert all(torch.equal(a[key][k], b[key][k]) for k in a[key]), key
    assert a["progress"]["updates"] == b["progress"]["updates"]
    # and its learning curve goes on as the straight run's: every column but the speed
    curves = [
        [row[:-1] for row in csv.reader((tmp_path / out / "progress.csv").open())]
        for out in ("a", "b")
    ]
    assert curves[0] == curves[1] and len(curves[0]) == 9


def test_a_run_stopped_at_any_moment_of_a_save_resumes_exactly_or_says_why_not(
    tmp_path, monkeypatch
):
    """The replay is written to a pending file before the checkpoint and moved in place after
    it. Stopped between the two, the run resumes from the pending replay; stopped while writing
    the next one, it passes over the half-written file; a replay of another step is refused."""
    flags = {"steps": 1600, "checkpoint_every": 400, **TINY}
    straight = load_checkpoint(train(TrainConfig(out=str(tmp_path / "a"), **flags), log=quiet))

    commits, commit = [], EpisodeReplay.commit

    def stop_before_the_second_commit(path):
        commits.append(path)
        if len(commits) == 2:
            raise KeyboardInterrupt
        commit(path)

    with monkeypatch.context() as patch:
        patch.setattr(EpisodeReplay, "commit", staticmethod(stop_before_the_second_commit))
        with pytest.raises(KeyboardInterrupt):
            train(TrainConfig(out=str(tmp_path / "b"), **flags), log=quiet)
    stopped = tmp_path / "b"
    assert load_checkpoint(stopped / "checkpoint.pt")["progress"]["steps"] == 800
    pending = EpisodeReplay.pending(stopped / "replay.npz")
    assert pending.is_file()
    mid_save, wrong_step = tmp_path / "mid_save", tmp_path / "wrong_step"
    shutil.copytree(stopped, mid_save)
    shutil.copytree(stopped, wrong_step)
    (mid_save / "replay.npz.pending").replace(mid_save / "replay.npz")
    (mid_save / "replay.npz.pending").write_bytes(
        pending.read_bytes()[: pending.stat().st_size // 2]
    )
    (wrong_step / "replay.npz.pending").unlink()

    for folder in (stopped, mid_save):
        resumed = load_checkpoint(
            train(TrainConfig(out=str(folder), **flags), resume=True, log=quiet)
        )
        for key in ("weights", "target_weights"):
            assert all(torch.equal(straight[key][k], resumed[key][k]) for k in straight[key])
        assert not (folder / "replay.npz.pending").exists()
    cli_flags = [f"--{k.replace('_', '-')}={v}" for k, v in flags.items()]
    refused = run_cli(*cli_flags, "--out", wrong_step, "--resume")
    one_line_exit_2(refused, "no replay saved at the checkpoint's step 800")


def test_learns_the_known_answer_one_agent_no_obstacles(tmp_path):
    """The identity-env habit: one agent, no obstacles; the oracle's score is optimal here."""
    cfg = TrainConfig(
        algo="udan",
        agents="1",
        obstacles="0",
        steps=64000,
        eps_fraction=0.3,
        updates_per_rollout=16,
        batch_episodes=16,
        out=str(tmp_path / "r"),
        checkpoint_every=1e9,
    )
    model, _ = load_model(train(cfg, log=quiet))
    learned = evaluate("arena/find_water", CheckpointPolicy(model), (1, 1), (0, 0), 50, seed=9)
    best = evaluate("arena/find_water", OraclePolicy(), (1, 1), (0, 0), 50, seed=9)
    assert learned[0].agent_score >= 0.95 * best[0].agent_score, (learned, best)


def test_every_config_field_is_documented_and_a_flag():
    docs = field_docs(TrainConfig)
    assert set(docs) == set(TrainConfig.__dataclass_fields__)
    out = subprocess.run([BIN / "udan-train", "--help"], capture_output=True, text=True).stdout
    assert all(f"--{name.replace('_', '-')}" in out for name in docs)


def run_cli(*args, tool="udan-train", timeout=120):
    return subprocess.run(
        [BIN / tool, *map(str, args)], capture_output=True, text=True, timeout=timeout
    )


def one_line_exit_2(proc, fragment):
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and fragment in lines[0], proc.stderr


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--algo", "sarsa"], "unknown algo"),
        (["--env", "arena/mars"], "unknown"),
        (["--env", "magent/queue", "--agents", "30"], "cannot line up"),
        (["--agents", "5-1"], "inverted"),
        (["--algo", "qmix", "--agents", "1-5"], "fixed number"),
        (["--out", "{blocked}/run"], "cannot create folder"),
        (["--leader-target", "rank"], "--leader-target must be one of"),
    ],
)
def test_bad_train_input(args, fragment, tmp_path):
    (tmp_path / "file").write_text("a file where a folder would go")
    args = [a.format(blocked=tmp_path / "file") for a in args]
    one_line_exit_2(
        run_cli("--steps", "10", *args, *([] if "--out" in args else ["--out", tmp_path / "r"])),
        fragment,
    )


def test_out_folders_are_made_as_needed(tmp_path):
    out = tmp_path / "runs" / "deep" / "fw"
    small = ["--steps", 200, "--n-envs", 4, "--batch-episodes", 4, "--hidden", 16]
    assert run_cli(*small, "--out", out).returncode == 0
    assert (out / "checkpoint.pt").is_file()


def test_resume_with_another_config_and_existing_run(tmp_path):
    out = tmp_path / "r"
    small = ["--steps", 200, "--n-envs", 4, "--batch-episodes", 4, "--hidden", 16]
    assert run_cli(*small, "--out", out).returncode == 0
    one_line_exit_2(run_cli(*small, "--out", out), "already holds a run")
    one_line_exit_2(run_cli(*small, "--out", out, "--resume", "--lr", 0.1), "config differs")
    one_line_exit_2(run_cli(*small, "--out", tmp_path / "none", "--resume"), "no checkpoint.pt")


def test_corrupt_truncated_and_foreign_checkpoints(tmp_path):
    good = train(TrainConfig(steps=200, out=str(tmp_path / "r"), **TINY), log=quiet)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(np.random.default_rng(0).bytes(4096))
    foreign = tmp_path / "foreign.pt"
    torch.save({"state_dict": {"w": torch.zeros(2)}}, foreign)
    for path in (truncated, garbage, foreign):
        with pytest.raises(CheckpointError):
            load_model(path)
        one_line_exit_2(run_cli(path, "--episodes", 1, tool="udan-eval"), str(path))
    one_line_exit_2(
        run_cli(good, "--env", "arena/surround", "--episodes", 1, tool="udan-eval"),
        "trained on arena/find_water",
    )


def test_leader_targets_signed_keeps_the_sign_minmax_the_batch_range():
    # Mostly small gains with one large one: every gain leads under "signed"; under the paper's
    # min-max only what lies above the midpoint of the batch's extremes does.
    delta = torch.tensor([-0.1, 0.05, 0.1, 0.2, 1.0])
    signed = leader_targets(delta, "signed")
    assert ((signed > 0.5) == (delta > 0)).all()
    assert signed.min() >= 0 and signed.max() == 1.0
    minmax = leader_targets(delta, "minmax")
    assert minmax.tolist() == pytest.approx([0.0, 0.136, 0.182, 0.273, 1.0], abs=1e-3)
    assert int((minmax > 0.5).sum()) == 1
    for mode in ("signed", "minmax"):
        assert leader_targets(torch.zeros(3), mode).tolist() == [0.5] * 3


def test_a_run_older_than_leader_target_resumes_as_minmax(tmp_path):
    cfg = TrainConfig(steps=160, out=str(tmp_path / "r"), leader_target="minmax", **TINY)
    train(cfg, log=quiet)
    ckpt = load_checkpoint(tmp_path / "r" / "checkpoint.pt")
    del ckpt["config"]["leader_target"]  # as written before the field existed
    torch.save(ckpt, tmp_path / "r" / "checkpoint.pt")
    train(dataclasses.replace(cfg, steps=320), resume=True, log=quiet)
    with pytest.raises(CheckpointError, match="leader_target"):
        train(dataclasses.replace(cfg, steps=480, leader_target="signed"), resume=True, log=quiet)
