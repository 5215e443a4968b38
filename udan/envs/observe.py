"""What a car sees: the one observation encoder for training, the edge masking and HIL.

An observation is the MAgent convention: an egocentric square window of radius ``view`` with
one binary plane per channel, followed by the agent's own features (normalised position, last
action one-hot, last reward). The edge runtime builds the same inputs from what the camera saw
and calls :func:`observe`, so a policy sees the same numbers on real cars as in training.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np

from udan.envs.rules import ACTIONS, N_ACTIONS

#: Bumped whenever the layout or meaning of an observation changes; exported models carry it.
OBS_SPEC_VERSION = 1

#: Spatial planes, in order. Bits of the packed cell code used by :func:`observe`.
CHANNELS: tuple[str, ...] = ("blocked", "agents", "objective")
BLOCKED_BIT, AGENT_BIT, OBJECTIVE_BIT = 1, 2, 4

FEATURES: tuple[str, ...] = (
    "row",
    "col",
    *(f"last_action_{i}" for i in range(N_ACTIONS)),
    "last_reward",
)


@dataclass(frozen=True)
class ObsSpec:
    """Shape and meaning of one agent's observation vector (a task with an observation of its
    own subclasses it with its own planes, features and version)."""

    height: int
    width: int
    view: int
    version: int = OBS_SPEC_VERSION
    channels: ClassVar[tuple[str, ...]] = CHANNELS
    features: ClassVar[tuple[str, ...]] = FEATURES
    actions: ClassVar[tuple[str, ...]] = ACTIONS
    """The policy's outputs, in order (the cars' five moves)."""

    @property
    def window(self) -> int:
        return 2 * self.view + 1

    @property
    def spatial_size(self) -> int:
        return len(self.channels) * self.window * self.window

    @property
    def size(self) -> int:
        return self.spatial_size + len(self.features)

    def to_dict(self) -> dict:
        return {**asdict(self), "channels": list(self.channels), "features": list(self.features)}


def pad_layout(codes: np.ndarray, view: int) -> np.ndarray:
    """Pad packed cell codes (B, H, W) by ``view`` cells of blocked border (off-arena is a wall).
    Filled and copied in, which costs a fifteenth of ``np.pad``."""
    batch, height, width = codes.shape
    padded = np.full((batch, height + 2 * view, width + 2 * view), BLOCKED_BIT, codes.dtype)
    padded[:, view : view + height, view : view + width] = codes
    return padded


def observe(
    spec: ObsSpec,
    padded_codes: np.ndarray,
    pos: np.ndarray,
    last_action: np.ndarray,
    last_reward: np.ndarray,
    present: np.ndarray,
) -> np.ndarray:
    """Observations (B, N, spec.size) float32; rows of absent agents are zero.

    ``padded_codes`` (B, H + 2v, W + 2v) uint8 holds the OR of ``*_BIT`` flags per cell, with
    every present agent's own cell carrying ``AGENT_BIT`` (cleared here from its own window).
    ``last_action`` is -1 before an agent's first move.
    """
    n_batch, n_agents = present.shape
    win = spec.window
    hp, wp = padded_codes.shape[1:]
    base = pos[..., 0] * wp + pos[..., 1]
    if n_batch > 1:
        base += (np.arange(n_batch) * (hp * wp))[:, None]
    cells = np.take(padded_codes, base[..., None] + _window_offsets(win, wp))  # (B, N, win*win)
    cells[..., (win * win) // 2] &= ~np.uint8(AGENT_BIT)
    out = np.empty((n_batch, n_agents, spec.size), dtype=np.float32)
    spatial = out[..., : spec.spatial_size].reshape(n_batch, n_agents, len(CHANNELS), win * win)
    np.not_equal(cells[..., None, :] & _BITS[:, None], 0, out=spatial)
    feat = out[..., spec.spatial_size :]
    np.divide(pos, (max(spec.height - 1, 1), max(spec.width - 1, 1)), out=feat[..., :2])
    np.equal(last_action[..., None], _ACTION_IDS, out=feat[..., 2 : 2 + N_ACTIONS])
    feat[..., -1] = last_reward
    out *= present[..., None]
    return out


_BITS = np.array([BLOCKED_BIT, AGENT_BIT, OBJECTIVE_BIT], dtype=np.uint8)
_ACTION_IDS = np.arange(N_ACTIONS)


@functools.cache
def _window_offsets(win: int, padded_width: int) -> np.ndarray:
    """Flat offsets of a ``win`` x ``win`` window's cells from its top-left cell."""
    return (np.arange(win)[:, None] * padded_width + np.arange(win)[None, :]).ravel()
