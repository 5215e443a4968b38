"""The sidecar shape: a child beside the loop that is fed without blocking and never outlives it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from udan.edge.sidecar import MESSAGE_BYTES, Outlet

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
    proc.kill()
    proc.wait()
    end = time.monotonic() + 10
    while time.monotonic() < end:
        if not _running(child):
            return
        time.sleep(0.05)
    os.kill(child, signal.SIGKILL)
    raise AssertionError("the child outlived its killed parent")


# A child with something to say at the end: how many records it read, and their sum.
COUNTER = textwrap.dedent(
    """
    import sys
    from udan.edge.sidecar import Inlet, ignore_interrupts
    ignore_interrupts()
    inlet = Inlet(int(sys.argv[2]))
    records = list(inlet)
    inlet.reply({"read": len(records), "sum": sum(records)})
    inlet.close()
    """
)


def test_the_child_replies_and_close_collects_it(tmp_path, monkeypatch):
    (tmp_path / "sidecar_counter.py").write_text(COUNTER)
    monkeypatch.setenv("PYTHONPATH", f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    outlet = Outlet("sidecar_counter")
    for k in range(100):
        assert outlet.offer(k)
    assert outlet.replies == []
    assert outlet.close() == "exit code 0"
    assert outlet.replies == [{"read": 100, "sum": 4950}]
