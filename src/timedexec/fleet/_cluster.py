"""Connecting to a Dask cluster (dask.distributed is the engine; there is no scheduler here).

:func:`connect` turns a scheduler address into a ``distributed.Client`` and checks that
the cluster can run timedexec (workers present, the same timedexec version), with messages
that say how to fix what is wrong. :func:`on_cluster` also routes joblib through the
cluster (``joblib.parallel_config(backend="dask")``), so that every library function that
fans out with ``jobs=-1`` (extraction, training, simulation) runs its tasks there.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from typing import Any

from timedexec._version import __version__
from timedexec.errors import ConfigError

__all__ = [
    "INSTALL_HINT",
    "SCHEDULER_ENV",
    "connect",
    "on_cluster",
    "parse_scheduler_address",
    "require_dask",
]

#: Environment variable holding the scheduler address when ``--scheduler`` is not given.
SCHEDULER_ENV = "TIMEDEXEC_SCHEDULER"
#: How to get dask.distributed.
INSTALL_HINT = "install it with: python3 -m pip install 'timedexec[dask]'"
#: Seconds to wait for the scheduler to answer, and for a first worker.
CONNECT_TIMEOUT_S = 10.0
WORKER_TIMEOUT_S = 30.0


def require_dask() -> Any:
    """Import and return ``distributed``.

    Raises
    ------
    ConfigError
        dask.distributed is not installed (the message says how to install it).
    """
    try:
        import distributed
    except ImportError as exc:
        raise ConfigError(
            f"running on a Dask cluster needs dask.distributed; {INSTALL_HINT}"
        ) from exc
    return distributed


def _worker_versions() -> dict[str, str]:
    """Run on a worker: what it would compute with."""
    import numpy
    import scipy

    import timedexec

    return {
        "timedexec": timedexec.__version__,
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "pid": str(os.getpid()),
    }


#: Address schemes a Dask scheduler listens on that this machine can reach.
_SCHEMES = ("tcp", "tls")
_ADDRESS_HELP = "give HOST:PORT or tcp://HOST:PORT (e.g. tcp://10.0.0.5:8786)"


def parse_scheduler_address(address: str) -> tuple[str, int]:
    """``(host, port)`` of a scheduler address ``[tcp://|tls://]HOST:PORT``.

    Raises
    ------
    ConfigError
        An empty or malformed address, another scheme, or a port outside 1 .. 65535; the
        message names the address and the form expected.
    """
    from urllib.parse import urlsplit

    text = address.strip()
    if not text:
        raise ConfigError(f"the scheduler address is empty; {_ADDRESS_HELP}")
    scheme = text.split("://", 1)[0].lower() if "://" in text else "tcp"
    if scheme not in _SCHEMES:
        raise ConfigError(
            f"scheduler address {address!r}: scheme {scheme!r} is not one of "
            f"{', '.join(_SCHEMES)}; {_ADDRESS_HELP}"
        )
    try:
        parts = urlsplit(text if "://" in text else f"tcp://{text}")
        host, port = parts.hostname, parts.port
    except ValueError as exc:
        raise ConfigError(
            f"scheduler address {address!r} is malformed ({exc}); {_ADDRESS_HELP}"
        ) from None
    if not host or port is None or parts.path not in ("", "/") or parts.query:
        raise ConfigError(f"scheduler address {address!r} is malformed; {_ADDRESS_HELP}")
    if not 1 <= port <= 65535:
        raise ConfigError(
            f"scheduler address {address!r}: port {port} is out of range; use 1 .. 65535"
        )
    return host, port


def _reach(address: str, host: str, port: int, timeout_s: float) -> None:
    """A TCP connection to the scheduler's port within ``timeout_s`` (no Dask yet), so a
    host that is down or a closed port is said plainly and at once."""
    import socket

    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as exc:
        raise ConnectionError(
            f"cannot reach the Dask scheduler at {address} within {timeout_s:g} s "
            f"({exc.strerror or exc}); start one (`dask scheduler`, then `dask worker "
            "ADDRESS` on each machine) or run without --scheduler on this machine"
        ) from None


def _is_scheduler(distributed: Any, address: str, timeout_s: float) -> None:
    """Ask the peer at ``address`` who it is (Dask's ``identity`` call), all of it bounded
    by ``timeout_s``, before a ``distributed.Client`` is made.

    A ``Client`` made against a peer that accepts and never speaks waited far past its own
    timeout, and one made against a peer that speaks another protocol failed after 20 s
    and left a client whose clean-up took 20 s more at exit. The question runs in a helper
    thread with its own event loop, so the main thread stays interruptible (Ctrl-C exits
    130 at once).

    Raises
    ------
    ConnectionError
        No answer within ``timeout_s``, an answer that is not Dask's, or not a scheduler's.
    """
    import asyncio
    import threading

    box: dict[str, Any] = {}

    async def ask() -> Any:
        comm = await asyncio.wait_for(
            distributed.comm.connect(address, timeout=timeout_s), timeout_s
        )
        try:
            await asyncio.wait_for(comm.write({"op": "identity", "reply": True}), timeout_s)
            return await asyncio.wait_for(comm.read(), timeout_s)
        finally:
            comm.abort()

    def run() -> None:
        try:
            box["reply"] = asyncio.run(asyncio.wait_for(ask(), timeout_s))
        except BaseException as exc:  # reported by the waiting thread
            box["error"] = exc

    thread = threading.Thread(target=run, name="timedexec-dask-identity", daemon=True)
    thread.start()
    thread.join(timeout_s + 1.0)
    error = box.get("error")
    if thread.is_alive() or isinstance(error, asyncio.TimeoutError | TimeoutError):
        raise ConnectionError(
            f"the peer at {address} accepted the connection but did not answer as a Dask "
            f"scheduler within {timeout_s:g} s; check the address and port (a Dask "
            "scheduler listens on 8786 by default) or run without --scheduler"
        )
    reply = box.get("reply")
    if error is not None or not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        what = (
            f"{type(error).__name__}: {str(error)[:120]}"
            if error is not None
            else f"it answered {str(reply)[:120]!r}"
        )
        raise ConnectionError(
            f"the peer at {address} is not a Dask scheduler ({what}); check the address "
            "and port, or run without --scheduler"
        )


def connect(
    address: str,
    *,
    timeout_s: float = CONNECT_TIMEOUT_S,
    worker_timeout_s: float = WORKER_TIMEOUT_S,
) -> Any:
    """A ``distributed.Client`` connected to the scheduler at ``address``, checked.

    Parameters
    ----------
    address : str
        Scheduler address, e.g. ``tcp://10.0.0.5:8786`` or ``10.0.0.5:8786``.
    timeout_s : float
        Seconds to wait for the scheduler, s.
    worker_timeout_s : float
        Seconds to wait for a first worker, s.

    Returns
    -------
    distributed.Client
        Close it when done (or use :func:`on_cluster`).

    Raises
    ------
    ConfigError
        dask.distributed missing, an empty or malformed address
        (:func:`parse_scheduler_address`), or workers whose timedexec is missing or of
        another version (results would not be the local run's).
    ConnectionError
        The scheduler's port cannot be reached, the peer does not answer as a Dask
        scheduler, within ``timeout_s`` (whatever it does: silent, garbage), or it has no
        worker within ``worker_timeout_s``.
    """
    distributed = require_dask()
    address = address.strip()
    host, port = parse_scheduler_address(address)
    _reach(address, host, port, timeout_s)
    _is_scheduler(distributed, address, timeout_s)
    try:
        client = distributed.Client(address, timeout=f"{timeout_s}s", set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise ConnectionError(
            f"cannot connect to the Dask scheduler at {address} within {timeout_s:g} s "
            f"({exc}); run without --scheduler on this machine"
        ) from exc
    try:
        try:
            client.wait_for_workers(1, timeout=worker_timeout_s)
        except (TimeoutError, OSError) as exc:
            raise ConnectionError(
                f"the Dask scheduler at {address} has no worker after {worker_timeout_s:g} s; "
                "start workers with `dask worker ADDRESS`"
            ) from exc
        try:
            versions = client.run(_worker_versions)
        except ImportError as exc:  # pragma: no cover - depends on the cluster
            raise ConfigError(
                f"the workers of {address} cannot import timedexec ({exc}); install the same "
                f"timedexec ({__version__}) on every worker"
            ) from exc
        wrong = {w: v["timedexec"] for w, v in versions.items() if v["timedexec"] != __version__}
        if wrong:
            shown = ", ".join(f"{w}: {v}" for w, v in sorted(wrong.items()))
            raise ConfigError(
                f"workers of {address} run another timedexec ({shown}) than this one "
                f"({__version__}); install the same version everywhere"
            )
    except BaseException:
        client.close()
        raise
    return client


@contextlib.contextmanager
def on_cluster(address: str | None) -> Iterator[Any]:
    """Run what is inside on the cluster at ``address``; with None, on this machine.

    Yields the connected ``distributed.Client`` (None without an address). Inside, joblib's
    default backend is the cluster (``joblib.parallel_config(backend="dask")``): library
    calls with ``jobs=-1`` spread their tasks over every worker. The client is closed on
    exit.

    Raises
    ------
    ConfigError, ConnectionError
        As :func:`connect`.
    """
    if address is None:
        yield None
        return
    client = connect(address, timeout_s=CONNECT_TIMEOUT_S, worker_timeout_s=WORKER_TIMEOUT_S)
    try:
        import joblib

        with joblib.parallel_config(
            backend="dask", client=client, wait_for_workers_timeout=WORKER_TIMEOUT_S
        ):
            yield client
    finally:
        client.close()
