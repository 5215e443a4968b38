"""The sidecar shape: a child beside the loop that is fed without blocking and never outlives it."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from udan.edge.sidecar import EXIT_WITH_PARENT, MESSAGE_BYTES, Outlet

# A listening child: writes every record it reads to the file named after --fd, one JSON a line.
ECHO = textwrap.dedent(
    """
    import json, sys
    from udan.edge.sidecar import ignore_interrupts, records
    ignore_interrupts()
    fd, out = int(sys.argv[2]), sys.argv[3]
    with open(out, "w") as f:
        for record in records(fd):
            f.write(json.dumps(record) + "\\n")
            f.flush()
    """
)


@pytest.fixture
def echo_module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    (tmp_path / "sidecar_echo.py").write_text(ECHO)
    monkeypatch.setenv("PYTHONPATH", f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    return "sidecar_echo"


def _running(pid: int) -> bool:
    """Alive and not a zombie (an orphan's exit may wait for init to reap it)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _lines(path: Path, n: int, timeout_s: float = 20.0) -> list:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if path.exists() and len(lines := path.read_text().splitlines()) >= n:
            return [json.loads(line) for line in lines]
        time.sleep(0.02)
    raise AssertionError(f"the child wrote {path.read_text() if path.exists() else 'nothing'}")


def test_records_arrive_in_order_and_the_child_ends_on_close(echo_module, tmp_path):
    out = tmp_path / "out.jsonl"
    outlet = Outlet(echo_module, [str(out)])
    assert all(outlet.offer({"i": i}) for i in range(100))
    assert [r["i"] for r in _lines(out, 100)] == list(range(100))
    assert outlet.close() == "exit code 0"
    assert (outlet.sent, outlet.dropped) == (100, 0)


def test_a_stalled_child_costs_drops_never_a_wait(echo_module, tmp_path):
    out = tmp_path / "out.jsonl"
    outlet = Outlet(echo_module, [str(out)], buffer_bytes=64 * 1024)
    _lines(out, 0)  # started
    outlet.offer({"i": -1})
    _lines(out, 1)
    os.kill(outlet.proc.pid, signal.SIGSTOP)
    try:
        start = time.monotonic()
        went = [outlet.offer({"i": i, "pad": "x" * 1000}) for i in range(2000)]
        elapsed = time.monotonic() - start
    finally:
        os.kill(outlet.proc.pid, signal.SIGCONT)
    assert elapsed < 2.0  # 2,000 offers; a blocking send would hang here forever
    assert not all(went) and any(went)
    assert outlet.dropped == went.count(False)
    # what went, arrives whole and in order after the stall
    arrived = [r["i"] for r in _lines(out, 1 + went.count(True))[1:]]
    assert arrived == [i for i, ok in enumerate(went) if ok]
    outlet.close()


def test_an_oversized_record_is_dropped_and_counted(echo_module, tmp_path):
    out = tmp_path / "out.jsonl"
    outlet = Outlet(echo_module, [str(out)])
    assert not outlet.offer({"blob": "y" * MESSAGE_BYTES})
    assert outlet.offer({"i": 1})
    assert _lines(out, 1) == [{"i": 1}]
    assert outlet.dropped == 1
    outlet.close()


def test_a_child_that_has_gone_is_counted_not_raised(echo_module, tmp_path):
    outlet = Outlet(echo_module, [str(tmp_path / "out.jsonl")])
    outlet.proc.kill()
    outlet.proc.wait()
    assert not outlet.alive
    assert not outlet.offer({"i": 1})
    assert outlet.dropped == 1
    assert outlet.close() == "killed by SIGKILL"


def _kill_and_expect_the_end_of(parent: subprocess.Popen, child: int) -> None:
    """SIGKILL ``parent``; ``child`` must end within 10 s."""
    parent.kill()
    parent.wait()
    end = time.monotonic() + 10
    while time.monotonic() < end:
        if not _running(child):
            return
        time.sleep(0.05)
    os.kill(child, signal.SIGKILL)
    raise AssertionError("the child outlived its killed parent")


def test_the_child_never_outlives_a_killed_parent(echo_module, tmp_path):
    """The edge SIGKILLed: its end of the socket closes with it, and the child ends by itself."""
    parent = textwrap.dedent(
        f"""
        import sys, time
        from udan.edge.sidecar import Outlet
        outlet = Outlet({echo_module!r}, [{str(tmp_path / "out.jsonl")!r}])
        print(outlet.proc.pid, flush=True)
        time.sleep(60)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", parent], stdout=subprocess.PIPE, text=True)
    child = int(proc.stdout.readline())
    _kill_and_expect_the_end_of(proc, child)


# A child that answers: replies {"got": i} to every record, and {"ready": true} first.
ANSWER = textwrap.dedent(
    """
    import sys
    from udan.edge.sidecar import Inlet, ignore_interrupts
    ignore_interrupts()
    inlet = Inlet(int(sys.argv[2]))
    inlet.reply({"ready": True})
    for record in inlet:
        if record == "quit":
            break
        inlet.reply({"got": record})
    inlet.reply({"bye": True})
    """
)


@pytest.fixture
def answer_module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    (tmp_path / "sidecar_answer.py").write_text(ANSWER)
    monkeypatch.setenv("PYTHONPATH", f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    return "sidecar_answer"


def test_replies_come_back_through_the_loop_and_the_end_is_told_once(answer_module):
    outlet = Outlet(answer_module)
    assert outlet.wait_reply(20.0) == {"ready": True}
    replies: list = []

    async def main() -> None:
        ended = asyncio.Event()

        def on_reply(reply) -> None:
            replies.append(reply)
            if reply is None:
                ended.set()

        outlet.listen(on_reply)
        for i in range(5):
            assert outlet.offer(i)
        outlet.offer("quit")
        await asyncio.wait_for(ended.wait(), 20)

    asyncio.run(main())
    assert replies == [*({"got": i} for i in range(5)), {"bye": True}, None]
    assert outlet.close() == "exit code 0"


def test_replies_nobody_listened_to_are_collected_at_close(answer_module):
    outlet = Outlet(answer_module)
    outlet.offer(7)
    assert outlet.close() == "exit code 0"  # EOF ends its loop: it says goodbye and exits
    assert outlet.replies == [{"ready": True}, {"got": 7}, {"bye": True}]


def test_no_reply_in_time_is_none_not_a_wait_forever(echo_module, tmp_path):
    outlet = Outlet(echo_module, [str(tmp_path / "out.jsonl")])
    start = time.monotonic()
    assert outlet.wait_reply(0.2) is None
    assert time.monotonic() - start < 2.0
    outlet.close()


WATCHED = textwrap.dedent(
    """
    import signal, sys, time
    from udan.edge.sidecar import exit_with_parent
    exit_with_parent()
    print("watching", flush=True)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    time.sleep(60)
    """
)


def test_a_child_asked_to_watch_its_parent_ends_when_the_parent_is_killed(tmp_path):
    (tmp_path / "watched.py").write_text(WATCHED)
    parent = textwrap.dedent(
        f"""
        import subprocess, sys, time
        from udan.edge.sidecar import parent_watch_env
        child = subprocess.Popen([sys.executable, {str(tmp_path / "watched.py")!r}],
                                 env=parent_watch_env(), start_new_session=True)
        print(child.pid, flush=True)
        time.sleep(60)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", parent], stdout=subprocess.PIPE, text=True)
    child = int(proc.stdout.readline())
    time.sleep(1.0)  # the child has started watching (a parent gone earlier is caught too)
    assert _running(child)
    _kill_and_expect_the_end_of(proc, child)


def test_without_the_request_a_child_is_not_bound_to_its_parent(tmp_path, monkeypatch):
    """An edge a user starts from a shell (nohup) must outlive the shell: no request, no watch;
    and the request is taken out of the environment, so grandchildren are not bound either."""
    monkeypatch.delenv(EXIT_WITH_PARENT, raising=False)
    probe = (
        "import os; from udan.edge.sidecar import exit_with_parent; exit_with_parent(); "
        f"print(os.environ.get({EXIT_WITH_PARENT!r}))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert out.stdout.strip() == "None"
    env = {**os.environ, EXIT_WITH_PARENT: str(os.getpid())}
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env)
    assert out.stdout.strip() == "None" and out.returncode == 0
