"""What ``udan-eval --ablate`` can switch off in a UDAN model at acting time (no torch here, so
the CLI can list and check them before playing); :class:`udan.learner.Actor` carries them out."""

#: Mode -> what it replaces, and nothing else.
ABLATIONS: dict[str, str] = {
    "messages=zero": "every message is zero (the Q head's Q_s)",
    "messages=shuffle": "each agent gets the message of its slot in another episode, same step",
    "groups": "every agent is a group of its own: the message path runs over the agent alone",
    "leaders=random": "as many leaders as the scorer picks, chosen at random among the agents",
    "leaders=all": "every agent leads a group (in the scorer's order)",
    "leaders=top-half": "the half of the agents (rounded up) the scorer ranks highest lead, "
    "whatever the threshold says",
    "leaders=random-half": "as many leaders as leaders=top-half, chosen at random among the agents",
}


def check_ablation(mode: str, algo: str, communicates: bool, episodes: int) -> None:
    """ValueError unless ``mode`` can be applied to a model of ``algo`` acting in ``episodes``
    episodes at once: a known mode, a model with messages, another episode to shuffle from."""
    if mode not in ABLATIONS:
        raise ValueError(f"--ablate: unknown mode {mode!r}; known: {', '.join(ABLATIONS)}")
    if not communicates:
        raise ValueError(f"--ablate: this {algo} model has no messages")
    if mode == "messages=shuffle" and episodes < 2:
        raise ValueError("--ablate messages=shuffle needs at least 2 episodes at once")
