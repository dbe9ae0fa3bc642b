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

__all__ = ["INSTALL_HINT", "SCHEDULER_ENV", "connect", "on_cluster", "require_dask"]

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
        dask.distributed missing, an empty address, or workers whose timedexec is missing
        or of another version (results would not be the local run's).
    ConnectionError
        The scheduler does not answer, or has no worker within ``worker_timeout_s``.
    """
    distributed = require_dask()
    address = address.strip()
    if not address:
        raise ConfigError(
            "the scheduler address is empty; give HOST:PORT (e.g. tcp://10.0.0.5:8786)"
        )
    try:
        client = distributed.Client(address, timeout=f"{timeout_s}s", set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise ConnectionError(
            f"cannot reach the Dask scheduler at {address} within {timeout_s:g} s ({exc}); "
            "start one (`dask scheduler`, then `dask worker ADDRESS` on each machine) or "
            "run without --scheduler on this machine"
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
    client = connect(address)
    try:
        import joblib

        with joblib.parallel_config(
            backend="dask", client=client, wait_for_workers_timeout=WORKER_TIMEOUT_S
        ):
            yield client
    finally:
        client.close()
