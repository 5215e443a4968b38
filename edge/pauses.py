"""Python's garbage collector and deadlines.

A full collection of cyclic garbage stops every thread of a process for as long as it takes to
scan every tracked object: ~14 ms in the edge (the model, OpenCV, the modules) and ~9 ms in the
HIL world that hosts the mock cars, more than a command's 10 ms deadline. What is loaded at
start lives as long as the process, so it is collected once and frozen: later collections never
scan it, and take a fraction of a millisecond.
"""

from __future__ import annotations

import gc


def freeze_garbage() -> None:
    """Collect once and freeze everything allocated so far. Call it before timing matters (in
    the edge, before the link starts: a time sync in flight during this one long collection
    would measure a round trip that long)."""
    gc.collect()
    gc.freeze()
