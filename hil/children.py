"""The HIL world's helper processes (the virtual camera, the cars' radios): spawned with a pipe,
ready or refused at start, told to stop and heard out."""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 10.0


class Child:
    """``target(conn, config)`` in a spawned process named ``name``. Its first message is
    ``("ready", value)``, kept in ``ready``, or ``("error", why)``, raised as an ``OSError`` that
    starts with ``what``."""

    def __init__(
        self,
        target: Callable[[Connection, Any], None],
        config: Any,
        *,
        name: str,
        what: str,
    ) -> None:
        context = multiprocessing.get_context("spawn")
        self.conn, child = context.Pipe()
        self.process = context.Process(target=target, args=(child, config), name=name, daemon=True)
        self.process.start()
        child.close()
        reply = self.conn.recv() if self.conn.poll(START_TIMEOUT_S) else ("error", "did not start")
        if reply[0] != "ready":
            self.process.join(timeout=5)
            raise OSError(f"{what}: {reply[1]}")
        self.ready = reply[1]

    def stop(self, request: Any) -> Any:
        """Send ``request`` (the child's cue to end), wait for its last word (``None`` if it had
        already gone), then for its end."""
        last = None
        try:
            self.conn.send(request)
            if self.conn.poll(STOP_TIMEOUT_S):
                last = self.conn.recv()[1]
        except (OSError, EOFError):
            pass
        self.process.join(timeout=5)
        if self.process.is_alive():
            self.process.terminate()
        return last
