"""The observation encoder shared by training, edge masking and HIL."""

import numpy as np
import pytest

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


def _previous_observe(spec, padded_codes, pos, last_action, last_reward, present):
    """observe as numpy arrays, before the loop moved to udan._kernels (commit b68a9ec): the
    oracle the C loop is held to."""
    n_batch, n_agents = present.shape
    win = spec.window
    hp, wp = padded_codes.shape[1:]
    base = pos[..., 0] * wp + pos[..., 1]
    if n_batch > 1:
        base += (np.arange(n_batch) * (hp * wp))[:, None]
    offsets = (np.arange(win)[:, None] * wp + np.arange(win)[None, :]).ravel()
    cells = np.take(padded_codes, base[..., None] + offsets)
    cells[..., (win * win) // 2] &= ~np.uint8(AGENT_BIT)
    out = np.empty((n_batch, n_agents, spec.size), dtype=np.float32)
    spatial = out[..., : spec.spatial_size].reshape(n_batch, n_agents, len(CHANNELS), win * win)
    bits = np.array([BLOCKED_BIT, AGENT_BIT, OBJECTIVE_BIT], dtype=np.uint8)
    np.not_equal(cells[..., None, :] & bits[:, None], 0, out=spatial)
    feat = out[..., spec.spatial_size :]
    np.divide(pos, (max(spec.height - 1, 1), max(spec.width - 1, 1)), out=feat[..., :2])
    np.equal(last_action[..., None], np.arange(5), out=feat[..., 2:7])
    feat[..., -1] = last_reward
    out *= present[..., None]
    return out


def test_observations_are_bit_for_bit_those_of_the_previous_array_code():
    """Random arenas, views and batches, absent agents with negative rewards (their zeros keep
    the sign, as x * 0 does), bits in any combination: the same bytes."""
    rng = np.random.default_rng(7)
    for _ in range(300):
        height, width, view = (int(v) for v in rng.integers(1, 12, 3))
        view = view % 4
        batch, n = int(rng.integers(1, 4)), int(rng.integers(1, 12))
        spec = ObsSpec(height, width, view)
        codes = rng.integers(0, 8, (batch, height, width)).astype(np.uint8)
        padded = pad_layout(codes, view)
        pos = np.stack(
            [rng.integers(0, height, (batch, n)), rng.integers(0, width, (batch, n))], -1
        )
        last_action = rng.integers(-1, 5, (batch, n))
        last_reward = rng.normal(size=(batch, n)).astype(np.float32)
        present = rng.random((batch, n)) < 0.7
        got = observe(spec, padded, pos, last_action, last_reward, present)
        want = _previous_observe(spec, padded, pos, last_action, last_reward, present)
        assert got.tobytes() == want.tobytes()
        out = np.full_like(want, np.nan)
        assert observe(spec, padded, pos, last_action, last_reward, present, out=out) is out
        assert out.tobytes() == want.tobytes()


def test_an_agent_off_its_arena_is_refused():
    spec = ObsSpec(3, 3, 1)
    padded = pad_layout(np.zeros((1, 3, 3), np.uint8), spec.view)
    one = np.ones((1, 1), bool)
    with pytest.raises(IndexError, match=r"agent 0 at \(3, 0\) sees past"):
        observe(spec, padded, np.array([[[3, 0]]]), np.zeros((1, 1), int), np.zeros((1, 1)), one)
