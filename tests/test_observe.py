"""The observation encoder shared by training, edge masking and HIL."""

import numpy as np

from udan.envs.observe import (
    AGENT_BIT,
    BLOCKED_BIT,
    CHANNELS,
    FEATURES,
    OBJECTIVE_BIT,
    ObsSpec,
    observe,
    pad_layout,
)


def planes(spec, vec):
    w = spec.window
    return vec[: spec.spatial_size].reshape(len(CHANNELS), w, w)


def test_window_contents_and_features():
    spec = ObsSpec(height=5, width=5, view=1)
    codes = np.zeros((1, 5, 5), np.uint8)
    codes[0, 1, 2] = BLOCKED_BIT  # obstacle above the agent at (2, 2)
    codes[0, 2, 3] = AGENT_BIT  # another agent to its right
    codes[0, 2, 2] = AGENT_BIT  # the agent itself
    codes[0, 3, 1] = OBJECTIVE_BIT
    padded = pad_layout(codes, spec.view)
    obs = observe(
        spec, padded, np.array([[[2, 2]]]), np.array([[3]]), np.array([[0.5]]), np.array([[True]])
    )
    assert obs.shape == (1, 1, spec.size) and obs.dtype == np.float32
    p = planes(spec, obs[0, 0])
    assert p[0].tolist() == [[0, 1, 0], [0, 0, 0], [0, 0, 0]]
    assert p[1].tolist() == [[0, 0, 0], [0, 0, 1], [0, 0, 0]], "self is not an 'other agent'"
    assert p[2].tolist() == [[0, 0, 0], [0, 0, 0], [1, 0, 0]]
    feat = obs[0, 0, spec.spatial_size :]
    assert len(feat) == len(FEATURES)
    assert feat[:2].tolist() == [0.5, 0.5]
    assert feat[2:7].tolist() == [0, 0, 0, 1, 0]
    assert feat[-1] == 0.5


def test_off_arena_is_blocked_and_absent_rows_are_zero():
    spec = ObsSpec(height=3, width=3, view=2)
    padded = pad_layout(np.zeros((1, 3, 3), np.uint8), spec.view)
    obs = observe(
        spec,
        padded,
        np.array([[[0, 0], [1, 1]]]),
        np.array([[-1, -1]]),
        np.zeros((1, 2)),
        np.array([[True, False]]),
    )
    blocked = planes(spec, obs[0, 0])[0]
    assert blocked[:2].all() and blocked[:, :2].all()  # two rows/cols off the arena
    assert blocked[2:, 2:].sum() == 0
    assert not obs[0, 0, spec.spatial_size + 2 : spec.spatial_size + 7].any(), "no last action"
    assert not obs[0, 1].any()


def test_spec_describes_the_vector():
    spec = ObsSpec(9, 9, 3)
    assert spec.size == 3 * 7 * 7 + 8
    d = spec.to_dict()
    assert d["version"] == spec.version and d["channels"] == list(CHANNELS)
