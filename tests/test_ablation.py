"""udan-eval --ablate, --probe and --leaders: each ablation changes exactly what it names; the
probe finds a goal where there is one; the leader table counts what the actor does; the CLIs end
to end on arena/hidden_goal."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from udan.envs import make_vec
from udan.evaluate import Z95, CellResult, format_paired
from udan.leaders import collect, format_leaders, group_ties, row
from udan.learner import Actor, ModelSpec, MultiAgentQ
from udan.probe import ridge_fit, ridge_r2

BIN = Path(sys.executable).parent
BATCH, AGENTS = 6, 6


def _model() -> MultiAgentQ:
    torch.manual_seed(0)
    model = MultiAgentQ(ModelSpec(algo="udan", obs_dim=25, n_actions=5, group_size=3))
    model.eval()
    return model


def _stream(steps: int = 7):
    """A recorded rollout of arena/hidden_goal (random moves): what every actor is fed."""
    env = make_vec("arena/hidden_goal", batch=BATCH, seed=4, agents=AGENTS, obstacles=0)
    obs, rng, out = env.reset(), np.random.default_rng(1), []
    for _ in range(steps):
        out.append((obs, env.present.copy(), env.pos.copy(), env.joined.copy()))
        obs, _, _ = env.step(rng.integers(0, 5, (BATCH, AGENTS)))
    return out


def _scores(model: MultiAgentQ, feats: torch.Tensor, pos, present) -> np.ndarray:
    """The leader classifier's probabilities (BATCH, AGENTS) from one step's features."""
    from udan.envs.grouping import neighbour_tables
    from udan.learner import neighbour_rows

    with torch.no_grad():
        tables = neighbour_tables(pos, present, model.spec.attention_neighbours)
        logits = model.leader(feats, neighbour_rows(tables))
    return torch.sigmoid(logits).view(BATCH, AGENTS).numpy()


def _play(model: MultiAgentQ, ablate: str | None) -> list[dict]:
    """Per step: groups, features and messages of an actor fed the recorded stream."""
    actor = Actor(model, BATCH, AGENTS, ablate, np.random.default_rng(2))
    steps = []
    for obs, present, pos, fresh in _stream():
        actor.act(obs, present, pos, fresh)
        steps.append(
            {
                "groups": [g.copy() for g in actor.groups],
                "feats": actor.feats.view(BATCH, AGENTS, -1).clone(),
                "messages": actor.messages.view(BATCH, AGENTS, -1).clone(),
                "prob": _scores(model, actor.feats, pos, present),
            }
        )
    return steps


@pytest.fixture(scope="module")
def plain_and_model():
    model = _model()
    # a threshold at the median leader probability: some agents lead, some do not
    obs, present, pos, fresh = _stream(1)[0]
    actor = Actor(model, BATCH, AGENTS)
    actor.act(obs, present, pos, fresh)
    prob = _scores(model, actor.feats, pos, present)
    model.spec = dataclasses.replace(model.spec, leader_threshold=float(np.median(prob)))
    return _play(model, None), model


def _same_groups(a: list[np.ndarray], b: list[np.ndarray]) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_messages_zero_only_zeroes_the_messages(plain_and_model):
    plain, model = plain_and_model
    for mine, base in zip(_play(model, "messages=zero"), plain, strict=True):
        assert _same_groups(mine["groups"], base["groups"])
        assert torch.equal(mine["feats"], base["feats"])
        assert not mine["messages"].any()
    assert any(step["messages"].any() for step in plain)


def test_messages_shuffle_hands_each_episode_anothers_messages(plain_and_model):
    plain, model = plain_and_model
    mine = _play(model, "messages=shuffle")
    for step, base in zip(mine, plain, strict=True):
        assert _same_groups(step["groups"], base["groups"])
        assert torch.equal(step["feats"], base["feats"])
        for b in range(BATCH):  # episode b's messages are those of another episode
            assert any(
                torch.equal(step["messages"][b], base["messages"][s])
                for s in range(BATCH)
                if s != b
            )
    assert not all(
        torch.equal(m["messages"], p["messages"]) for m, p in zip(mine, plain, strict=True)
    )


def test_groups_ablation_puts_every_agent_in_a_group_of_its_own(plain_and_model):
    plain, model = plain_and_model
    mine = _play(model, "groups")
    for step, base in zip(mine, plain, strict=True):
        assert torch.equal(step["feats"], base["feats"])
        for groups in step["groups"]:
            assert groups.shape == (AGENTS, 1)
            assert groups[:, 0].tolist() == list(range(AGENTS))
    assert not all(
        torch.equal(m["messages"], p["messages"]) for m, p in zip(mine, plain, strict=True)
    )


def test_random_leaders_are_as_many_as_the_learned_ones(plain_and_model):
    plain, model = plain_and_model
    mine = _play(model, "leaders=random")
    for step, base in zip(mine, plain, strict=True):
        counts = [len(g) for g in step["groups"]]
        assert counts == [len(g) for g in base["groups"]]
    assert not all(_same_groups(m["groups"], p["groups"]) for m, p in zip(mine, plain, strict=True))


def _leaders(step: dict) -> list[list[int]]:
    return [sorted(g[:, 0].tolist()) for g in step["groups"]]


def test_top_half_leaders_are_the_half_the_scorer_ranks_highest(plain_and_model):
    plain, model = plain_and_model
    top = _play(model, "leaders=top-half")
    for step in top[:: model.spec.group_interval]:  # the steps that form groups
        for groups, prob in zip(step["groups"], step["prob"], strict=True):
            ranked = np.argsort(-prob, kind="stable")[: (AGENTS + 1) // 2]
            assert sorted(groups[:, 0].tolist()) == sorted(ranked.tolist())
            assert groups.shape[1] == model.spec.group_size
    for mine, base in zip(top, plain, strict=True):
        assert torch.equal(mine["feats"], base["feats"])
    # the threshold (the fixture's median) lets another share lead at some formation
    assert any(len(g) != (AGENTS + 1) // 2 for step in plain for g in step["groups"])
    random = _play(model, "leaders=random-half")
    for step in random:
        assert all(len(g) == (AGENTS + 1) // 2 for g in step["groups"])
    assert any(_leaders(r) != _leaders(t) for r, t in zip(random, top, strict=True))


def test_all_leaders_means_a_group_per_agent_led_by_it(plain_and_model):
    plain, model = plain_and_model
    for step in _play(model, "leaders=all"):
        for groups in step["groups"]:
            assert sorted(groups[:, 0].tolist()) == list(range(AGENTS))
            assert groups.shape[1] == model.spec.group_size
    assert any(len(g) < AGENTS for step in plain for g in step["groups"])


def test_ablations_refuse_a_model_without_messages():
    spec = ModelSpec(algo="udan", obs_dim=25, n_actions=5, messages=False)
    with pytest.raises(ValueError, match="has no messages"):
        Actor(MultiAgentQ(spec), 2, 2, "messages=zero")


def test_probe_finds_a_goal_in_a_message_that_carries_it_and_none_in_one_that_does_not():
    rng = np.random.default_rng(0)
    mix = rng.normal(size=(2, 16))  # how the sender writes the goal into the message

    def data(n: int, carries: bool):
        goal = rng.integers(0, 9, (n, 2)).astype(float)
        noise = rng.normal(size=(n, 16))
        message = noise + (goal @ mix if carries else 0.0)
        return message, goal

    train, test = data(3000, True), data(3000, True)
    assert ridge_r2(ridge_fit(*train), *test) > 0.9
    train, test = data(3000, False), data(3000, False)
    assert abs(ridge_r2(ridge_fit(*train), *test)) < 0.02


def test_ablation_table_pairs_episodes_per_n_and_pools_every_n_in_its_last_row():
    def cells(scores_by_n):
        return [
            CellResult(n, 0, len(s), float(np.mean(s)), 0.0, scores=np.array(s, dtype=float))
            for n, s in scores_by_n.items()
        ]

    full = cells({2: [4.0, 6.0, 8.0], 3: [2.0, 2.0, 2.0]})
    shuffled = cells({2: [3.0, 5.0, 7.0], 3: [1.0, 1.0, 3.4]})  # pooled: -1 five times, +1.4 once
    table = format_paired(full, {"messages=shuffle": shuffled}, "t")
    assert "| 2 | 6.00 | 5.00 | -1.00 [-1.00, -1.00] | -17 % |" in table
    pooled = -3.6 / 6
    half = Z95 * np.std([-1, -1, -1, -1, -1, 1.4], ddof=1) / np.sqrt(6)
    assert table.splitlines()[-1] == (
        f"| 2-3 pooled | 4.00 | 3.40 | {pooled:+.2f} [{pooled - half:+.2f}, {pooled + half:+.2f}]"
        " | -15 % |"
    )
    single = format_paired(full[:1], {"messages=shuffle": shuffled[:1]}, "t")
    assert "pooled" not in single
    nothing = cells({2: [0.0, 0.0]})
    assert "| 2 | 0.00 | 0.00 | +0.00 [+0.00, +0.00] | — |" in format_paired(
        nothing, {"groups": nothing}, "t"
    )
    losing = format_paired(cells({2: [-4.0, -2.0]}), {"groups": cells({2: [-5.0, -3.0]})}, "t")
    assert "| 2 | -3.00 | -4.00 | -1.00 [-1.00, -1.00] | -33 % |" in losing  # a loss stays a loss


def test_leader_row_counts_leaders_gains_and_the_min_max_midpoint():
    prob = np.array([0.9, 0.8, 0.2, 0.1, 0.6])
    delta = np.array([0.5, 0.1, 0.05, -0.2, -1.0])  # one large loss moves min-max's midpoint
    ties = np.array([[0, 1, 5], [1, 3, 5], [2, 5, 5], [3, 5, 5], [1, 3, 5]])  # groups, reach, N
    r = row(3, prob, delta, 0.5, ties)
    assert r.candidates == 5
    assert r.values["leading"] == pytest.approx(0.6)
    assert r.values["ΔQ > 0"] == pytest.approx(0.6)
    assert r.values["min-max target > 0.5"] == pytest.approx(0.8)  # midpoint at -0.25
    assert r.values["mean ΔQ of leaders"] == pytest.approx((0.5 + 0.1 - 1.0) / 3)
    assert r.values["mean ΔQ of others"] == pytest.approx((0.05 - 0.2) / 2)
    assert r.ties == {
        "in no group": 0.2,
        "in 1": 0.4,
        "in 2": 0.2,
        "in 3 or more": 0.2,
        "mean reach": pytest.approx(3.4),
        "reach: whole fleet": 0.4,
    }
    everyone = row(3, np.ones(5), delta, 0.5, ties)
    assert np.isnan(everyone.values["mean ΔQ of others"])
    text = format_leaders([everyone], "t")
    assert "| 3 | 5 | 100.0 % | 60.0 % | 80.0 % |" in text
    assert "| 3 | 20.0 % | 40.0 % | 20.0 % | 20.0 % | 3.4 | 40.0 % |" in text


def test_group_ties_count_distinct_groups_and_reach_through_bridges():
    present = np.array([True, True, True, True, True, False, True])
    groups = np.array([[0, 1], [1, 2], [3, 4], [4, 3]])  # 1 bridges two; [4, 3] is [3, 4] again
    counts, reach, fleet = group_ties(groups, present).T
    assert counts.tolist() == [1, 2, 1, 1, 1, 0]  # slots 0-4 and 6, in slot order
    assert reach.tolist() == [3, 3, 3, 2, 2, 1] and fleet.tolist() == [6] * 6
    chain = group_ties(np.array([[0, 1], [1, 2], [2, 3]]), np.ones(4, bool))
    assert chain[:, 1].tolist() == [4, 4, 4, 4]  # two bridges deep: reach needs the closure
    counts, reach, _ = group_ties(np.zeros((0, 3), np.int64), present).T
    assert counts.tolist() == [0] * 6 and reach.tolist() == [1] * 6


def test_leader_table_sees_the_leaders_the_actor_forms_groups_with(plain_and_model):
    _, model = plain_and_model
    prob, delta, ties = collect(model, "arena/hidden_goal", AGENTS, 0, BATCH, seed=4)
    # hidden_goal lasts 20 steps, groups form every 5: 4 formations of BATCH arenas of AGENTS,
    # every one present, and (N > k) every one a candidate leader
    formations = -(-20 // model.spec.group_interval)
    assert len(prob) == len(delta) == formations * BATCH * AGENTS
    assert len(ties) == formations * BATCH * AGENTS
    env = make_vec("arena/hidden_goal", batch=BATCH, seed=4, agents=AGENTS, obstacles=0)
    obs, actor, leaders, members = env.reset(), Actor(model, BATCH, AGENTS), 0, 0
    for step in range(20):
        actions = actor.act(obs, env.present, env.pos, env.joined)
        if step % model.spec.group_interval == 0:
            leaders += sum(len(g) for g in actor.groups)
            members += sum(np.unique(np.sort(g, axis=1), axis=0).size for g in actor.groups)
        obs, _, _ = env.step(actions)
    assert int((prob > model.spec.leader_threshold).sum()) == leaders
    counts, reach, fleet = ties.T
    assert int(counts.sum()) == members and (reach >= 1).all() and (fleet == AGENTS).all()
    assert (reach <= AGENTS).all()
    assert np.isfinite(delta).all() and delta.std() > 0


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(args, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_train_ablate_probe_and_export_through_the_real_clis(tmp_path):
    common = ["--env", "arena/hidden_goal", "--agents", "2-3", "--obstacles", "0"]
    common += ["--steps", "640", "--n-envs", "8", "--batch-episodes", "8"]
    for name, extra in (("udan", []), ("quiet", ["--messages", "off"])):
        out = _run(str(BIN / "udan-train"), *common, *extra, "--out", str(tmp_path / name))
        assert out.returncode == 0, out.stderr
    ckpt = str(tmp_path / "udan" / "checkpoint.pt")
    out = _run(
        str(BIN / "udan-eval"),
        ckpt,
        "--agents",
        "2-3",
        "--obstacles",
        "0",
        "--episodes",
        "30",
        "--ablate",
        "messages=shuffle,leaders=all,leaders=top-half,leaders=random-half",
        "--probe",
        "--leaders",
        "--out",
        str(tmp_path),
    )
    assert out.returncode == 0, out.stderr
    report = (tmp_path / "report.md").read_text()
    assert "no-message bound" in report and "Δ messages=shuffle" in report
    assert "R² shuffled message" in report
    # the top half against random leaders: each one's Δ to the full model, and to each other
    ablations = report.split("ablations, paired")[1].split("\n\n")[1]
    pooled = next(line for line in ablations.splitlines() if "pooled" in line).split(" | ")
    top, random = (float(pooled[i].split(" [")[0]) for i in (9, 12))  # their Δ to the full
    same = report.split("top half against random leaders at the same share")[1].split("\n\n")[1]
    row = next(line for line in same.splitlines() if "pooled" in line).split(" | ")
    assert float(row[1]) == pytest.approx(float(pooled[11]), abs=0.006)  # random-half's score
    assert float(row[3].split(" [")[0]) == pytest.approx(top - random, abs=0.011)
    assert "| 2 | " in report.split("leaders against ΔQ")[1]
    out = _run(str(BIN / "udan-export"), ckpt, "-o", str(tmp_path / "policy.onnx"))
    assert out.returncode == 0, out.stdout + out.stderr
    assert "verdict: PASS" in out.stdout
    # its observation is not the cars' one: the edge refuses it in one line
    edge = _run(str(BIN / "udan-edge"), "--sim", "--model", str(tmp_path / "policy.onnx"))
    assert edge.returncode == 2 and "not an arena task the cars can play" in edge.stderr
    curves = _run(
        str(BIN / "udan-eval"),
        "--curves",
        str(tmp_path / "udan"),
        str(tmp_path / "quiet"),
        "--out",
        str(tmp_path),
    )
    assert curves.returncode == 0 and "| quiet | 640 |" in curves.stdout, curves.stderr
    assert (tmp_path / "curves.png").stat().st_size > 1000
    quiet = str(tmp_path / "quiet" / "checkpoint.pt")
    for flag in (["--ablate", "messages=zero"], ["--probe"], ["--leaders"]):
        out = _run(str(BIN / "udan-eval"), quiet, "--agents", "2", "--obstacles", "0", *flag)
        assert out.returncode == 2
        assert out.stderr.count("\n") == 1 and "has no" in out.stderr
