"""What ``udan-eval --ablate`` can switch off in a UDAN model at acting time (no torch here, so
the CLI can list them before loading a model); :class:`udan.learner.Actor` carries them out."""

#: Mode -> what it replaces, and nothing else.
ABLATIONS: dict[str, str] = {
    "messages=zero": "every message is zero (the Q head's Q_s)",
    "messages=shuffle": "each agent gets the message of its slot in another episode, same step",
    "groups": "every agent is a group of its own: the message path runs over the agent alone",
    "leaders=random": "as many leaders as the scorer picks, chosen at random among the agents",
    "leaders=all": "every agent leads a group (in the scorer's order)",
}
