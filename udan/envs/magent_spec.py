"""The observation of the MAgent scenarios as a spec (numpy-free and without magent2, so the
export metadata and the edge, which must tell such a policy apart, can read it).

The layout is :mod:`udan.envs.magent`'s: MAgent2's view window flattened (rows, columns, channel
last), MAgent2's features (id embedding, last action one-hot, last reward), then the position.
Its actions are MAgent2's: the moves of the agent's speed circle, then its attacks.
"""

from __future__ import annotations

from dataclasses import dataclass

from udan.envs.observe import ObsSpec

SPEC_NAME = "magent"
#: Bumped whenever the MAgent observation layout or meaning changes.
SPEC_VERSION = 1
#: MAgent2 id embedding width (the value its own scenarios use).
EMBEDDING_SIZE = 10


@dataclass(frozen=True)
class MagentSpec(ObsSpec):
    """Shape and meaning of one learning agent's observation in a MAgent scenario."""

    scenario: str = "magent/pursuit"
    opponents: bool = True
    """The scenario has an opponent group (its presence and hp are two more view planes)."""
    n_moves: int = 5
    n_attacks: int = 0
    version: int = SPEC_VERSION
    name: str = SPEC_NAME

    @property
    def channels(self) -> tuple[str, ...]:
        mine = ("wall", "team", "team_hp")
        return (*mine, "opponent", "opponent_hp") if self.opponents else mine

    @property
    def actions(self) -> tuple[str, ...]:
        return (
            *(f"move_{i}" for i in range(self.n_moves)),
            *(f"attack_{i}" for i in range(self.n_attacks)),
        )

    @property
    def features(self) -> tuple[str, ...]:
        return (
            *(f"embedding_{i}" for i in range(EMBEDDING_SIZE)),
            *(f"last_action_{i}" for i in range(len(self.actions))),
            "last_reward",
            "x",
            "y",
        )
