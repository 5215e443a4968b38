"""What pauses the event loop past a deadline, and how the edge avoids it.

Python's garbage collector: a full collection of cyclic garbage stops every thread of a process
for as long as it takes to scan every tracked object: ~14 ms in the edge (the model, OpenCV,
the modules) and ~9 ms in the HIL world that hosts the mock cars, more than a command's 10 ms
deadline. What is loaded at start lives as long as the process, so it is collected once and
frozen: later collections never scan it, and take a fraction of a millisecond.

The scheduler: with two cores shared by the camera, vision, and (in the HIL) the world, the
event loop can wait ~10 ms for a core now and then, which costs a step all its commands.
``run_realtime`` (``udan-edge --realtime``) puts the loop's thread under round-robin real-time
scheduling, so no ordinary thread holds it up; it needs ``CAP_SYS_NICE`` (root, or ``setcap``).
"""

from __future__ import annotations

import gc
import os
from pathlib import Path

REALTIME_PRIORITY = 10  # SCHED_RR priority (1-99): above every ordinary thread, far below IRQs
PERCEPTION_PRIORITY = 5
"""The perception process's SCHED_RR priority under ``--realtime``: below the loop, which
preempts it for every send, and above every ordinary thread (a camera's driver, a renderer, a
web page), which then cannot hold a frame's analysis up."""
#: Every this many collections between steps, a full one (the others: the youngest objects).
FULL_COLLECTION_EVERY = 100


def freeze_garbage() -> None:
    """Collect once and freeze everything allocated so far. Call it before timing matters (in
    the edge, before the link starts: a time sync in flight during this one long collection
    would measure a round trip that long)."""
    gc.collect()
    gc.freeze()


def collect_between_steps(count: int) -> None:
    """The collection the edge runs between two steps, with automatic collection disabled: the
    young objects, and every ``FULL_COLLECTION_EVERY``-th (``count`` from 0) all of them but
    the frozen ones."""
    gc.collect(2 if count % FULL_COLLECTION_EVERY == 0 else 0)


def run_realtime(priority: int = REALTIME_PRIORITY) -> None:
    """Schedule the calling thread ``SCHED_RR`` at ``priority``; raises ``PermissionError``
    without ``CAP_SYS_NICE``. Threads and processes it starts later run ordinary
    (``SCHED_RESET_ON_FORK``): the perception process and the ``--sim`` world must not outrank
    it."""
    os.sched_setscheduler(0, os.SCHED_RR | os.SCHED_RESET_ON_FORK, os.sched_param(priority))


def threads_of_this_process() -> list[int]:
    """The native ids of this process's threads (libraries start some of their own); none
    where ``/proc`` does not list them."""
    tasks = Path("/proc/self/task")
    return [int(task.name) for task in tasks.iterdir()] if tasks.is_dir() else []


def run_process_realtime(priority: int = PERCEPTION_PRIORITY) -> None:
    """Schedule every thread of this process ``SCHED_RR`` at ``priority``, and the threads they
    start later with it; raises ``PermissionError`` without ``CAP_SYS_NICE``."""
    for tid in threads_of_this_process():
        os.sched_setscheduler(tid, os.SCHED_RR, os.sched_param(priority))


def scheduler() -> str:
    """The calling thread's scheduling policy, for the report."""
    policy = os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK
    return {os.SCHED_RR: "SCHED_RR", os.SCHED_FIFO: "SCHED_FIFO"}.get(policy, "SCHED_OTHER")
