"""udan-eval --tags: what a checkpoint makes of random attacks, counted right and refused where
it cannot apply."""

import math

import pytest

from udan.checkpoint import load_model
from udan.envs import EnvConfigError
from udan.evaluate import main
from udan.tags import tag_values
from udan.train import TrainConfig, train

TINY = {"steps": 160, "n_envs": 4, "batch_episodes": 4, "hidden": 16, "max_steps": 20}


def _trained(tmp_path, env: str, algo: str = "udan", agents: str = "2-3"):
    """A tiny checkpoint of ``algo`` on ``env``'s 12×12 map."""
    out = str(tmp_path / algo)
    config = TrainConfig(env=env, algo=algo, agents=agents, out=out, map_size=12, **TINY)
    return train(config, log=lambda *a, **k: None)


def test_the_attacks_add_up_to_what_the_wolves_scored(tmp_path):
    """On a map where random wolves meet wandering sheep, every attack is counted once, paid or
    not, and the tags and attack costs add up to the episodes' returns (+1 a tag, −0.2 an
    attack, nothing else in pursuit)."""
    model, _ = load_model(_trained(tmp_path, "magent/pursuit"))
    options = {"map_size": 7, "max_steps": 20, "prey_alertness": 0.0}
    rows = tag_values(model, "magent/pursuit", (2, 3), 4, 0, **options)
    assert [row.agents for row in rows] == [2, 3]
    for row in rows:
        assert 0 < row.paid < row.attacks
        assert row.paid - 0.2 * row.attacks == pytest.approx(row.returned, abs=1e-3)
        assert row.paid_greedy <= row.paid_above_moves  # the greedy action beats every move


@pytest.mark.parametrize("algo", ["vdn", "iql", "udan", "qmix"])
def test_the_mixer_gradient_is_what_each_mixer_passes_back(tmp_path, algo):
    """VDN's sum passes back exactly 1 to every agent's Q; IQL has no Q_tot (NaN), nor QMIX at
    another N or on another map than its hypernetwork mixes; UDAN's and QMIX's non-negative
    weights pass back a positive share."""
    agents = "3" if algo == "qmix" else "2-3"
    model, _ = load_model(_trained(tmp_path, "magent/pursuit", algo, agents))
    rows = tag_values(model, "magent/pursuit", (2, 3), 2, 0, map_size=12, max_steps=20)
    gradient = {row.agents: row.mixer_gradient for row in rows}
    (other_map,) = tag_values(model, "magent/pursuit", (3, 3), 1, 0, map_size=7, max_steps=5)
    assert math.isnan(other_map.mixer_gradient) == (algo in ("iql", "qmix"))
    if algo == "vdn":
        assert gradient == {2: pytest.approx(1.0), 3: pytest.approx(1.0)}
    elif algo == "iql":
        assert all(math.isnan(g) for g in gradient.values())
    elif algo == "qmix":
        assert math.isnan(gradient[2]) and 0 < gradient[3] < math.inf
    else:
        assert all(0 < g < math.inf for g in gradient.values())


def test_the_cli_prints_a_row_per_fleet_size(tmp_path, capsys):
    path = _trained(tmp_path, "magent/pursuit")
    args = [str(path), "--tags", "--agents", "2-3", "--episodes", "2", "--map-size", "8"]
    assert main([*args, "--prey-alertness", "0"]) == 0
    out = capsys.readouterr().out
    assert "what it makes of random attacks (2 episodes per N, sheep alertness 0, 8×8 map)" in out
    assert "| 2 | " in out and "| 3 | " in out and "| ∂Q_tot/∂Q_i |" in out


@pytest.mark.parametrize(
    ("env", "algo", "message"),
    [
        ("magent/queue", "udan", "--tags needs a task whose agents attack"),
        ("magent/pursuit", "coma", "--tags reads Q values; a coma checkpoint has a policy"),
    ],
)
def test_what_has_no_attacks_or_no_q_values_is_refused(tmp_path, capsys, env, algo, message):
    agents = "3" if algo == "coma" else "2-3"
    path = _trained(tmp_path, env, algo, agents)
    assert main([str(path), "--tags", "--episodes", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    with pytest.raises(EnvConfigError, match="--tags"):
        tag_values(load_model(path)[0], env, (3, 3), 1, 0, map_size=12)


def test_tags_take_one_checkpoint_and_no_reference_policy(tmp_path, capsys):
    path = _trained(tmp_path, "magent/pursuit")
    assert main([str(path), "--tags", "--policy", "chaser", "--episodes", "1"]) == 2
    assert "take exactly one checkpoint and no --policy" in capsys.readouterr().err
