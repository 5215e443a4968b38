"""Processes beside the control loop: started with a socket pair, fed without ever blocking it.

Anything that runs beside the loop — the perception, a recorder, a web view — runs in a process
of its own (a thread would take turns with the loop at the interpreter lock). They share one
shape:

- :func:`spawn` starts ``python -m MODULE --fd N ...`` with its end of a Unix ``SOCK_SEQPACKET``
  socket pair: one message per send, in order, never merged. The child runs in a process group
  of its own (a Ctrl-C on the terminal is the edge's to handle) but in the edge's session
  (Linux's autogroup shares the CPU between sessions first: a session of its own would stand
  level with the loop whatever its niceness). It ends when its end of the socket reads EOF, so
  it never outlives the edge, however the edge ended (even SIGKILL).
- :class:`Outlet` is the loop's side of a child that only listens: :meth:`Outlet.offer` pickles
  a record and sends it if the socket has room, else drops and counts it. The socket's buffer is
  the bound; the loop never waits for the child.
- :func:`records` is the child's side: every record until the edge closes its end. A child
  with something to say reads through an :class:`Inlet` and :meth:`Inlet.reply` s on the same
  socket: at the end (what it wrote, what it missed), which :meth:`Outlet.close` collects
  (:attr:`Outlet.replies`) once the child has exited; or while the loop runs (the web view's
  stop button), which the loop reads with ``add_reader`` (:meth:`Outlet.listen`); or before
  it runs (a child saying it is ready: :meth:`Outlet.wait_reply`).
- :func:`exit_with_parent` is for processes that are not sidecars (the HIL world, an edge a
  harness starts): asked to by their parent, they get SIGTERM when it dies, however it died.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import os
import pickle
import select
import signal
import socket
import subprocess
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

STOP_TIMEOUT_S = 3.0
"""Longest the edge waits for a child told to stop to exit before it is killed."""
EXIT_STATUS_WAIT_S = 1.0
"""Longest an error message waits for a child that closed its socket to exit."""
MESSAGE_BYTES = 1 << 16
"""Largest message either side reads at once."""


def spawn(module: str, args: Sequence[str] = ()) -> tuple[socket.socket, subprocess.Popen]:
    """Start ``python -m module --fd N *args``; returns the edge's end of the socket pair and the
    process. The child's end is closed here once the child holds it."""
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    cmd = [sys.executable, "-m", module, "--fd", str(theirs.fileno()), *args]
    try:
        proc = subprocess.Popen(
            cmd, pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL, process_group=0
        )
    except BaseException:
        ours.close()
        raise
    finally:
        theirs.close()
    return ours, proc


def exit_of(proc: subprocess.Popen) -> str:
    """How a process ended, in words (waiting a moment at most)."""
    try:  # a killed process closes its files a moment before its exit status is ready
        code = proc.wait(EXIT_STATUS_WAIT_S)
    except subprocess.TimeoutExpired:
        return "its socket closed"
    if code < 0:
        with contextlib.suppress(ValueError):
            return f"killed by {signal.Signals(-code).name}"
    return f"exit code {code}"


def reap(proc: subprocess.Popen, timeout_s: float = STOP_TIMEOUT_S) -> None:
    """Wait for a process told to stop; kill it if it does not."""
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def ignore_interrupts() -> None:
    """In a child: SIGINT and SIGTERM are the edge's to handle (it stops the cars first, then
    its children)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)


class Outlet:
    """A bounded channel from the control loop to a listening child process that never blocks
    the loop: a record the socket has no room for is dropped and counted."""

    def __init__(self, module: str, args: Sequence[str] = (), *, buffer_bytes: int = 1 << 20):
        """Start the child; ``buffer_bytes`` bounds what may wait in the socket for it."""
        self.module = module
        self.sent = 0
        self.dropped = 0
        """Records the socket had no room for (the child is behind) or that were too large."""
        self.replies: list[Any] = []
        """What the child replied (:meth:`Inlet.reply`) and no listener took, collected by
        :meth:`close`."""
        self._sock, self.proc = spawn(module, args)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, buffer_bytes)
        self._sock.setblocking(False)
        self._listening: asyncio.AbstractEventLoop | None = None

    @property
    def alive(self) -> bool:
        """The child has not ended."""
        return self.proc.poll() is None

    def offer(self, record: Any) -> bool:
        """Send ``record`` if there is room now; returns whether it went. Never waits."""
        if self._sock.fileno() < 0:
            self.dropped += 1
            return False
        data = pickle.dumps(record, protocol=pickle.HIGHEST_PROTOCOL)
        if len(data) > MESSAGE_BYTES:  # the child would read it cut short
            self.dropped += 1
            return False
        try:
            self._sock.send(data)
        except OSError:  # no room (BlockingIOError), or the child has gone
            self.dropped += 1
            return False
        self.sent += 1
        return True

    def wait_reply(self, timeout_s: float) -> Any | None:
        """The child's next reply, waiting up to ``timeout_s`` (before the loop runs: a child
        saying it is ready); None if none came or the child has gone."""
        if self._sock.fileno() < 0 or not select.select([self._sock], [], [], timeout_s)[0]:
            return None
        return next(self._waiting(), None)

    def _waiting(self) -> Iterator[Any | None]:
        """The replies waiting in the socket now; a last None when the child has gone."""
        while True:
            try:
                data = self._sock.recv(MESSAGE_BYTES)
            except BlockingIOError:
                return
            except OSError:
                data = b""
            if not data:
                yield None
                return
            yield pickle.loads(data)

    def listen(self, on_reply: Callable[[Any | None], None]) -> None:
        """Hand every reply of the child to ``on_reply`` in the running loop (``add_reader``),
        and None once when the child has gone."""
        loop = asyncio.get_running_loop()
        fd = self._sock.fileno()

        def readable() -> None:
            for reply in self._waiting():
                if reply is None:
                    loop.remove_reader(fd)
                    self._listening = None
                on_reply(reply)

        loop.add_reader(fd, readable)
        self._listening = loop

    def close(self, timeout_s: float = STOP_TIMEOUT_S) -> str:
        """Close the edge's end (the child reads EOF, finishes what it holds and exits) and
        wait for it; one that does not exit in time is killed. Returns how it ended."""
        if self._listening is not None:
            with contextlib.suppress(RuntimeError):  # the loop has closed: nothing to remove
                self._listening.remove_reader(self._sock.fileno())
            self._listening = None
        if self._sock.fileno() >= 0:
            with contextlib.suppress(OSError):
                self._sock.shutdown(socket.SHUT_WR)
            reap(self.proc, timeout_s)
            with contextlib.suppress(OSError):  # the child has exited: what it sent is all here
                while data := self._sock.recv(MESSAGE_BYTES):
                    self.replies.append(pickle.loads(data))
            self._sock.close()
        return exit_of(self.proc)


class Inlet:
    """The child's end of an :class:`Outlet`: every record the edge offers (iterate), and
    replies the edge reads (:meth:`Outlet.listen`, :meth:`Outlet.wait_reply`) or collects when
    it closes the outlet."""

    def __init__(self, fd: int) -> None:
        self._sock = socket.socket(fileno=fd)

    def __iter__(self) -> Iterator[Any]:
        """Every record, in order, until the edge closes its end or goes away."""
        buffer = bytearray(MESSAGE_BYTES)
        while True:
            try:
                size = self._sock.recv_into(buffer)
            except OSError:
                return
            if not size:
                return
            yield pickle.loads(memoryview(buffer)[:size])

    def reply(self, record: Any) -> bool:
        """Send ``record`` back (small: it must fit one message); False if the edge has gone.
        Safe from another thread than the one iterating."""
        try:
            self._sock.send(pickle.dumps(record, protocol=pickle.HIGHEST_PROTOCOL))
        except OSError:
            return False
        return True

    def close(self) -> None:
        self._sock.close()


def records(fd: int) -> Iterator[Any]:
    """In the child: every record the edge offers, in order, until the edge closes its end or
    goes away."""
    inlet = Inlet(fd)
    try:
        yield from inlet
    finally:
        inlet.close()


EXIT_WITH_PARENT = "UDAN_EXIT_WITH_PARENT"
"""Environment variable a parent sets (to its pid) to ask a child to die with it."""
_PR_SET_PDEATHSIG = 1


def parent_watch_env(env: Mapping[str, str] | None = None) -> dict[str, str]:
    """The environment for a child that is to end with this process (see
    :func:`exit_with_parent`): ``env`` (default: ours) asking it to."""
    return {**(os.environ if env is None else env), EXIT_WITH_PARENT: str(os.getpid())}


def exit_with_parent() -> None:
    """If the parent asked (:func:`parent_watch_env`), have the kernel send this process SIGTERM
    when the parent ends, however it ends (Linux ``PR_SET_PDEATHSIG``; elsewhere nothing). The
    request is taken out of the environment, so this process's own children are not bound to
    it. A parent that has already gone by now is answered with SIGTERM at once. The parent must
    start the child from a thread that lives as long as it does (the signal follows the thread)."""
    parent = os.environ.pop(EXIT_WITH_PARENT, None)
    if parent is None or not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) != 0:
            return
    if str(os.getppid()) != parent:
        os.kill(os.getpid(), signal.SIGTERM)
