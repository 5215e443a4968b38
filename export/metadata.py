"""What an exported policy carries in ``metadata_props``, and the check the edge makes on it.

A policy is only correct with the observation layout, action order and grouping constants it was
trained with; none of these is visible in the graph's shapes. So every exported file carries them,
and :func:`check_metadata` compares them with the running code before a car is driven. No torch
here: the edge imports this module.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from udan.envs import code_spec
from udan.envs.observe import ObsSpec

FORMAT = "udan-policy"
FORMAT_VERSION = 4

#: Every key an exported policy has, with what it means (also the list ``verify`` reports from).
KEYS: dict[str, str] = {
    "format": f"always {FORMAT!r}",
    "format_version": "layout of the graph's inputs and outputs (export/README.md)",
    "algo": "udan, qmix, vdn, iql or coma",
    "env": "environment the policy was trained on",
    "obs_spec": "observation spec as JSON (udan.envs.observe.ObsSpec.to_dict)",
    "obs_spec_version": "udan.envs.observe.OBS_SPEC_VERSION at training time",
    "view_radius": "observation window radius in cells",
    "obs_dim": "length of one observation vector",
    "actions": "action names in output order, JSON list",
    "hidden": "width of the recurrent state h and c",
    "communicates": "1 if the graph takes groups (UDAN), else 0",
    "group_size": "k: a leader and its k-1 nearest agents form a group",
    "group_interval": "T: steps between group formations",
    "leader_threshold": "leader probability above which an agent leads",
    "attention_neighbours": "K: columns of the neighbours input",
    "checkpoint_sha256": "sha256 of the checkpoint file the weights come from",
    "project_version": "udan-edge version that exported the file",
}


class MetadataError(ValueError):
    """A policy file whose metadata is missing or does not match the running code."""


def project_version() -> str:
    try:
        return version("udan-edge")
    except PackageNotFoundError:  # running from a source tree that is not installed
        return "unknown"


def build_metadata(
    ckpt: Mapping[str, Any], spec: Mapping[str, Any], checkpoint_sha256: str
) -> dict[str, str]:
    """The metadata of a policy exported from checkpoint dict ``ckpt`` (all values strings).

    ``spec`` is the loaded model's ``ModelSpec`` as a dict: it fills fields that checkpoints
    older than a field lack with the default the model was built with.
    """
    obs = ckpt["obs_spec"]
    return {
        "format": FORMAT,
        "format_version": str(FORMAT_VERSION),
        "algo": ckpt["algo"],
        "env": ckpt["env"],
        "obs_spec": json.dumps(obs, sort_keys=True),
        "obs_spec_version": str(obs["version"]),
        "view_radius": str(obs["view"]),
        "obs_dim": str(spec["obs_dim"]),
        "actions": json.dumps(list(code_spec(obs).actions)),
        "hidden": str(spec["hidden"]),
        "communicates": "1" if spec["algo"] == "udan" and spec.get("messages", True) else "0",
        "group_size": str(spec["group_size"]),
        "group_interval": str(spec["group_interval"]),
        "leader_threshold": repr(float(spec["leader_threshold"])),
        "attention_neighbours": str(spec["attention_neighbours"]),
        "checkpoint_sha256": checkpoint_sha256,
        "project_version": project_version(),
        # not in KEYS: policies exported before it lack it and still load
        "agents": str(ckpt["config"]["agents"]),
    }


def missing_keys(meta: Mapping[str, str]) -> list[str]:
    return [key for key in KEYS if key not in meta]


def check_metadata(meta: Mapping[str, str], expected: ObsSpec | None = None) -> None:
    """Raise :class:`MetadataError` unless ``meta`` fits this code (and ``expected``, if given).

    Checked: every key present, the file format, the observation spec version, channels and
    features, the action order, and with ``expected`` the arena size and view radius the edge
    will observe with. The message names every problem at once.
    """
    missing = missing_keys(meta)
    if missing:
        raise MetadataError(f"not a udan policy: metadata missing {', '.join(missing)}")
    problems = []
    if meta["format"] != FORMAT or meta["format_version"] != str(FORMAT_VERSION):
        problems.append(
            f"format {meta['format']} v{meta['format_version']} is not {FORMAT} v{FORMAT_VERSION}"
        )
    obs = json.loads(meta["obs_spec"])
    code = code_spec(obs)
    if obs.get("version") != code.version:
        problems.append(f"observation spec v{obs.get('version')} is not v{code.version}")
    if tuple(obs.get("channels", ())) != code.channels or tuple(obs.get("features", ())) != (
        code.features
    ):
        problems.append("observation channels/features differ from this code's")
    if tuple(json.loads(meta["actions"])) != code.actions:
        problems.append(f"actions {meta['actions']} are not {list(code.actions)}")
    if expected is not None:
        want = {k: v for k, v in asdict(expected).items() if k != "version"}
        got = {k: obs.get(k) for k in want}
        if got != want:
            problems.append(f"observation spec {got} is not the edge's {want}")
    if problems:
        raise MetadataError("; ".join(problems))


def obs_spec(meta: Mapping[str, str]) -> ObsSpec:
    """The :class:`ObsSpec` a policy was trained with (after :func:`check_metadata`)."""
    obs = json.loads(meta["obs_spec"])
    return ObsSpec(obs["height"], obs["width"], obs["view"], obs["version"])
