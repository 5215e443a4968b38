"""Today's decision step against streams recorded with the previous implementation
(``tests/decision_streams.py``, its ``PREVIOUS`` commit): fleets of 1 to 1,000 cars with churn,
bridged groups, cars off their cells or still moving, and rehearsals; every decision, reward,
group and observation must come out bit for bit as recorded."""

from __future__ import annotations

import gzip
import hashlib
import json

import pytest
from decision_streams import DEFAULT_MODEL, DEFAULT_OUT, SCENARIOS, replay

from udan.edge.decide import DecisionStep, task_of
from udan.envs.arena import ArenaConfig
from udan.export.runtime import OnnxPolicy


@pytest.fixture(scope="module")
def streams() -> dict:
    with gzip.open(DEFAULT_OUT, "rt") as f:
        streams = json.load(f)
    if streams["model_sha256"] != hashlib.sha256(DEFAULT_MODEL.read_bytes()).hexdigest():
        pytest.fail(
            f"{DEFAULT_OUT.name} was recorded for another {DEFAULT_MODEL}: regenerate it with "
            "`.venv/bin/python tests/decision_streams.py` (it runs the previous implementation)"
        )
    return streams


@pytest.mark.parametrize("scenario", SCENARIOS, ids=lambda s: s.name)
def test_decisions_are_those_of_the_previous_implementation(streams, scenario) -> None:
    events = streams["scenarios"][scenario.name]
    sizes = [len(e["slots"]) for e in events if "slots" in e]
    assert min(sizes) >= scenario.agents[0] and max(sizes) <= scenario.agents[1]
    cfg = ArenaConfig(
        task=scenario.task, agents=scenario.agents, height=scenario.size, width=scenario.size
    )
    step = DecisionStep(OnnxPolicy(DEFAULT_MODEL), task_of(f"arena/{scenario.task}"), cfg.spec)
    for t, (want, got) in enumerate(zip(events, replay(step, events), strict=True)):
        assert got == want, f"{scenario.name}: event {t} differs"
