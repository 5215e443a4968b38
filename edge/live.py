"""The loop's side of the operator's web view (``udan-edge --web HOST:PORT``).

The web server runs in a process of its own (:mod:`udan.edge.web`), started through
:class:`udan.edge.sidecar.Outlet`: the loop offers it a snapshot at most every ``PERIOD_NS``,
taken when the loop is about to wait for the camera anyway (never between a frame's scene and its
decision), and the newest camera thumbnail the perception process drew; a snapshot the socket
has no room for is dropped and counted, never waited for. The way back is one request, the
page's stop-all button: the loop reads it with ``add_reader`` on the same socket and stops every
car through the link (the car protocol's authenticated ESTOP), then says how many cars it sent
the stop to.
"""

from __future__ import annotations

import importlib.util
import ipaddress
from collections.abc import Callable
from typing import Any

from udan.edge.sidecar import Outlet
from udan.edge.transport import TransportError, host_port

PERIOD_NS = 100_000_000
"""At most one snapshot every 100 ms: the page updates at ≤ 10 Hz."""
START_TIMEOUT_S = 30.0
"""Longest the edge waits for the web process to bind its address (a cold start imports
aiohttp and prometheus_client from disk)."""
MIN_TOKEN_CHARS = 16
TOKEN_HINT = "python -c 'import secrets; print(secrets.token_urlsafe(24))'"


class WebError(ValueError):
    """The web view cannot be served as asked; one line."""


def web_address(text: str, token: str | None) -> tuple[str, int]:
    """``HOST:PORT`` of ``--web`` (a port alone is on 127.0.0.1); a non-loopback host needs a
    token, and a token must be long enough to guess at no better than chance. The web view's
    libraries must be installed."""
    missing = [m for m in ("aiohttp", "prometheus_client") if not importlib.util.find_spec(m)]
    if missing:
        raise WebError(f"--web needs {' and '.join(missing)}: pip install 'udan-edge[web]'")
    try:
        host, port = host_port(f"127.0.0.1:{text}" if text.isdigit() else text, "--web")
    except TransportError as err:
        raise WebError(str(err)) from None
    if token is not None and len(token) < MIN_TOKEN_CHARS:
        raise WebError(
            f"--web-token: at least {MIN_TOKEN_CHARS} characters (make one with {TOKEN_HINT})"
        )
    if token is None and not _loopback(host):
        raise WebError(
            f"--web {text}: serving beyond this machine needs --web-token (anyone who can reach "
            f"the page could stop the fleet without it)"
        )
    return host, port


def _loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:  # a name: it may resolve to anything
        return False


class LiveView:
    """The web process and what the loop sends it; see the module docstring."""

    def __init__(self, host: str, port: int, token: str | None, config: dict[str, Any]) -> None:
        """Start the web process (it binds while the caller goes on: :meth:`wait_ready`).
        ``config`` is what the page needs to know of the run (arena size, car ids)."""
        missing = [m for m in ("aiohttp", "prometheus_client") if not importlib.util.find_spec(m)]
        if missing:
            raise WebError(f"--web needs {' and '.join(missing)}: pip install 'udan-edge[web]'")
        bind = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
        self._outlet = Outlet("udan.edge.web", ["--bind", bind])
        self._outlet.offer(("config", {**config, "token": token}))
        self.url: str | None = None
        self.ended = False
        """The web process has gone (the run goes on without a page)."""
        self.last_step: dict[str, Any] | None = None
        self._next_ns = 0
        self._thumbnail: bytes | None = None
        self._on_estop: Callable[[], int] | None = None

    @property
    def dropped(self) -> int:
        """Records the web process was too far behind to take."""
        return self._outlet.dropped

    def wait_ready(self) -> str:
        """Until the web process serves; its address, or a :class:`WebError` (the address is in
        use, cannot be bound, or the process did not start)."""
        if self.url is not None:
            return self.url
        reply = self._outlet.wait_reply(START_TIMEOUT_S)
        if reply is None:
            raise WebError(f"the web view did not start ({self._outlet.close()})")
        if reply["kind"] == "error":
            self._outlet.close()
            raise WebError(reply["message"])
        self.url = reply["url"]
        return self.url

    def start(self, on_estop: Callable[[], int]) -> None:
        """In the running loop: stop requests from the page call ``on_estop`` (it stops every
        car and returns how many it sent the stop to)."""
        self._on_estop = on_estop
        self._outlet.listen(self._reply)

    def _reply(self, reply: dict[str, Any] | None) -> None:
        """A message of the web process (None: it has gone)."""
        if reply is None:
            self.ended = True
        elif reply.get("kind") == "estop" and self._on_estop is not None:
            cars = self._on_estop()
            self._outlet.offer(("estopped", {"id": reply["id"], "cars": cars}))

    def step(self, record: dict[str, Any]) -> None:
        """The step just dispatched: the page draws the last one."""
        self.last_step = record

    def due(self, now_ns: int) -> bool:
        """Whether a snapshot is due: at most one every ``PERIOD_NS``, on a fixed grid (an
        occasion a little late does not delay the ones after it)."""
        if self.ended or now_ns < self._next_ns:
            return False
        self._next_ns = max(self._next_ns + PERIOD_NS, now_ns - PERIOD_NS // 2)
        return True

    def publish(self, snapshot: dict[str, Any], thumbnail: bytes | None) -> None:
        """Offer ``snapshot`` (built by the caller when :meth:`due`), and ``thumbnail`` if it
        is a new one."""
        if thumbnail is not None and thumbnail is not self._thumbnail:
            self._thumbnail = thumbnail
            self._outlet.offer(("thumbnail", thumbnail))
        self._outlet.offer(("state", {**snapshot, "live_dropped": self._outlet.dropped}))

    def close(self) -> str:
        """Stop the web process (it reads the end of the socket); how it ended."""
        return self._outlet.close()
