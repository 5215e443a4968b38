"""Ray for one command: ``udan-train --workers``, ``udan-eval --workers``, ``udan-sweep``.

Only these commands import this module, and only when asked for workers or a cluster: Ray is
an optional extra (``pip install udan-edge[scale]``) and the edge never imports it.

:func:`ray_session` starts a small local Ray for one command, sized for a shared machine (the
CPUs asked for, no dashboard, an object store as large as the command's data needs, logs kept
out of the command's output, token authentication on), or joins the cluster at ``--address``;
it always shuts Ray down, however the command ends. An address that cannot be reached is a
:class:`ScaleError` within :data:`PROBE_SECONDS`, never a hang.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any


class ScaleError(ValueError):
    """A cluster that cannot be reached or used: the CLIs say so in one line, exit code 2."""


log = logging.getLogger(__name__)
#: An ``--address`` where nothing answers, or nothing that speaks gRPC, is reported within
#: this many seconds of trying: with the command's start-up (2 s, more on a loaded machine),
#: within 10 s. A cluster's GCS or client server answers a probe in milliseconds.
PROBE_SECONDS = 4.0
#: Joining what answers there may take longer (a Ray client server starts a process for each
#: client): it is given up after this many seconds.
JOIN_SECONDS = 60.0
#: Ray's client server starts a process per client; now and then (seen on a loaded 2-core
#: machine: that process dead within half a second of its start) it fails to, and the client
#: is refused with "Initialization failure from server". One more try is a new process.
CLIENT_INIT_TRIES = 2
#: Ray's smallest object store; ours is the command's need, at least this.
MIN_OBJECT_STORE = 80 * 1024**2
#: Ray's settings unless the environment says otherwise, read when Ray is imported: no usage
#: report sent over the network; token authentication (Ray's default for a local Ray) chosen
#: explicitly, so Ray does not print a notice about it. A cluster without authentication is
#: joined with RAY_AUTH_MODE=disabled.
RAY_ENVIRONMENT = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "token"}


#: What a command asked for workers says when the ``scale`` extra is not installed.
NEEDS_RAY = "workers need Ray: pip install 'udan-edge[scale]' (Ray is an optional extra)"


def import_ray():
    """The ``ray`` module, imported with :data:`RAY_ENVIRONMENT`; :class:`ScaleError` naming
    the extra when it is not installed."""
    for key, value in RAY_ENVIRONMENT.items():
        os.environ.setdefault(key, value)
    try:
        import ray
    except ImportError:
        raise ScaleError(NEEDS_RAY) from None
    return ray


def check_address(address: str, timeout: float, name: str = "") -> None:
    """Refuse, within ``timeout`` seconds, an ``--address`` that is malformed, where nothing
    answers, or where what answers is not Ray: no gRPC, or gRPC (any HTTP/2 server, a proxy)
    that does not know the call a Ray GCS (``HOST:PORT``) or client server (``ray://``)
    answers. Ray itself would retry such an address for minutes (and log a line a second).
    ``name``: how the user wrote it."""
    name = f"{name} ({address})" if name else address
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise ScaleError(f"--address {name!r}: expected ray://HOST:PORT, HOST:PORT or auto")
    started = time.monotonic()
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout / 2).close()
    except OSError as err:
        reason = err.strerror or type(err).__name__
        raise ScaleError(f"--address {name}: no Ray cluster answers there ({reason})") from None
    try:
        import grpc  # comes with Ray's client (the scale extra)
    except ImportError:
        raise ScaleError(NEEDS_RAY) from None
    with grpc.insecure_channel(f"{host}:{port}") as channel:
        try:
            grpc.channel_ready_future(channel).result(timeout - (time.monotonic() - started))
        except grpc.FutureTimeoutError:
            raise ScaleError(
                f"--address {name}: what answers there is not a Ray cluster (no gRPC)"
            ) from None
        call, request = _ray_call(channel, client=address.startswith("ray://"))
        try:
            call(request, timeout=max(timeout - (time.monotonic() - started), 0.1))
        except grpc.RpcError as err:
            if err.code() not in (
                grpc.StatusCode.UNAUTHENTICATED,
                grpc.StatusCode.PERMISSION_DENIED,
            ):
                raise ScaleError(
                    f"--address {name}: what answers there is not a Ray cluster "
                    f"(its gRPC answered Ray's call with {err.code().name})"
                ) from None


def _ray_call(channel, *, client: bool) -> tuple[Any, Any]:
    """The cheapest call the Ray at the other end answers: the client server's ping, or the
    GCS's cluster id (a cluster that wants a token refuses it: still Ray, and Ray's own join
    says what is wrong)."""
    if client:
        from ray.core.generated import ray_client_pb2, ray_client_pb2_grpc

        stub = ray_client_pb2_grpc.RayletDriverStub(channel)
        return stub.ClusterInfo, ray_client_pb2.ClusterInfoRequest(
            type=ray_client_pb2.ClusterInfoType.PING
        )
    from ray.core.generated import gcs_service_pb2, gcs_service_pb2_grpc

    stub = gcs_service_pb2_grpc.NodeInfoGcsServiceStub(channel)
    return stub.GetClusterId, gcs_service_pb2.GetClusterIdRequest()


class _SilenceThreadNotice(logging.Filter):
    """Ray notes that it cannot set its SIGTERM handler when connecting off the main thread,
    which :func:`_join` does on purpose (so a silent address cannot hang the command)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "SIGTERM handler is not set" not in record.getMessage()


def auto_address() -> str:
    """The cluster ``--address auto`` means, found as Ray finds it (``RAY_ADDRESS``, a Ray
    running on this machine, the last one started here), so it can be probed like any other.
    Ray's own resolver, which is not public API: the ``scale`` extra pins Ray's version."""
    from ray._private.services import canonicalize_bootstrap_address

    try:
        found = canonicalize_bootstrap_address("auto")
    except (ConnectionError, ValueError) as err:
        raise ScaleError(f"--address auto: {str(err).strip().splitlines()[0]}") from None
    if found is None:
        raise ScaleError("--address auto: no Ray cluster runs on this machine")
    return found


def _join(ray, address: str) -> None:
    """``ray.init(address)``, once :func:`check_address` found it answering (``ray_session``
    probed any other address before importing Ray), within :data:`JOIN_SECONDS`, or
    :class:`ScaleError`."""
    if address == "auto":
        check_address(auto_address(), PROBE_SECONDS, "auto")
    outcome: dict[str, BaseException | None] = {}

    def connect() -> None:
        for attempt in range(1, CLIENT_INIT_TRIES + 1):
            try:
                ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
                outcome["error"] = None
                return
            except ConnectionAbortedError as err:  # ray://: the server's process for us failed
                outcome["error"] = err
                if attempt < CLIENT_INIT_TRIES:
                    log.warning("--address %s: %s; trying again", address, _said(err))
            except Exception as err:  # handed to the caller's thread below
                outcome["error"] = err
                return

    notice = _SilenceThreadNotice()
    logging.getLogger("ray._private.worker").addFilter(notice)
    try:
        thread = threading.Thread(target=connect, name="ray-connect", daemon=True)
        thread.start()
        thread.join(JOIN_SECONDS)
    finally:
        logging.getLogger("ray._private.worker").removeFilter(notice)
    if "error" not in outcome:
        raise ScaleError(
            f"--address {address}: no answer from a Ray cluster within {JOIN_SECONDS:.0f} s"
        )
    if outcome["error"] is not None:
        raise ScaleError(f"--address {address}: {_said(outcome['error'])}")


def _said(err: BaseException) -> str:
    """An error in one line: its first, and when that only announces what follows (Ray's
    client passes on the server's whole traceback), the last too."""
    lines = [line.strip() for line in str(err).strip().splitlines() if line.strip()]
    if not lines:
        return type(err).__name__
    said = lines[0] if len(lines) == 1 or not lines[0].endswith(":") else f"{lines[0]} {lines[-1]}"
    return said[:200]


@contextmanager
def ray_session(cpus: int, address: str = "", object_store_bytes: int = 0) -> Iterator[int]:
    """Ray for one command; yields the CPUs it offers.

    Without ``address``: a local Ray of ``cpus`` CPUs (one per worker), no dashboard, an object
    store of ``object_store_bytes`` (at least Ray's minimum), Ray's logs in its session folder
    only. With ``address``: that cluster joined. Ray is shut down on the way out.
    """
    if address and address != "auto":
        check_address(address, PROBE_SECONDS)  # before Ray's import: a bad address fails fast
    ray = import_ray()
    if ray.is_initialized():
        raise ScaleError("Ray is already running in this process")
    try:
        if address:
            _join(ray, address)
        else:
            ray.init(
                address="local",  # a new local Ray, even where another one runs
                num_cpus=cpus,
                include_dashboard=False,
                object_store_memory=max(object_store_bytes, MIN_OBJECT_STORE),
                logging_level=logging.WARNING,
                log_to_driver=False,
            )
        yield int(ray.cluster_resources().get("CPU", 0))
    finally:
        if ray.is_initialized():
            ray.shutdown()


def ray_map(fn: Callable, calls: Sequence[tuple]) -> list:
    """``[fn(*args) for args in calls]`` as Ray tasks of one CPU each, in the connected Ray;
    results in the order of ``calls``."""
    ray = import_ray()
    remote = ray.remote(num_cpus=1)(fn)
    return ray.get([remote.remote(*args) for args in calls])
