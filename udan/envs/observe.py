"""What a car sees: the one observation encoder for training, the edge masking and HIL.

An observation is the MAgent convention: an egocentric square window of radius ``view`` with
one binary plane per channel, followed by the agent's own features (normalised position, last
action one-hot, last reward). The edge runtime builds the same inputs from what the camera saw
and calls :func:`observe`, so a policy sees the same numbers on real cars as in training.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np

from udan import _kernels
from udan.envs.rules import ACTIONS, N_ACTIONS

#: Bumped whenever the layout or meaning of an observation changes; exported models carry it.
OBS_SPEC_VERSION = 1

#: Spatial planes, in order. Bits of the packed cell code used by :func:`observe`.
CHANNELS: tuple[str, ...] = ("blocked", "agents", "objective")
BLOCKED_BIT, AGENT_BIT, OBJECTIVE_BIT = 1, 2, 4
_BITS = np.array([BLOCKED_BIT, AGENT_BIT, OBJECTIVE_BIT], dtype=np.uint8)  # per channel

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
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Observations (B, N, spec.size) float32 (into ``out`` if given); rows of absent agents are
    zero.

    ``padded_codes`` (B, H + 2v, W + 2v) uint8 holds the OR of ``*_BIT`` flags per cell, with
    every present agent's own cell carrying ``AGENT_BIT`` (cleared here from its own window).
    ``last_action`` is -1 before an agent's first move. One pass per agent, window and
    features (``udan._kernels.observe``); a present agent stands on its arena (IndexError
    otherwise).
    """
    present = np.ascontiguousarray(present, bool)
    if out is None:
        out = np.empty((*present.shape, spec.size), np.float32)
    _kernels.observe(
        np.ascontiguousarray(padded_codes, np.uint8),
        np.ascontiguousarray(pos, np.int64),
        np.ascontiguousarray(last_action, np.int64),
        np.ascontiguousarray(last_reward, np.float32),
        present,
        _BITS,
        spec.view,
        AGENT_BIT,
        max(spec.height - 1, 1),
        max(spec.width - 1, 1),
        out,
    )
    return out
