"""``--scheduler ADDRESS``: the commands that fan out run on a Dask cluster.

Shared by ``extract``, ``train``, ``discrepancy`` and ``fleet`` (and meant for ``simulate``
and ``evaluate``). With an address (``--scheduler``, else the environment variable
``TIMEDEXEC_SCHEDULER``), a command connects to that scheduler and routes its joblib work
through it (``joblib.parallel_config(backend="dask")``, every worker used); work that does
not fan out is sent as one task. Without one it runs on this machine, as before. Results
are the local run's (docs/fleet.md says where and to what tolerance).

Files a command reads on the cluster must be readable by every worker at the same path
(shared storage): paths are made absolute before they are sent. ``--scheduler ''`` runs
on this machine even when the environment variable is set.
"""

from __future__ import annotations

import argparse
import contextlib
import os
from collections.abc import Callable, Iterator
from typing import Any

from timedexec.cli._common import note, used_jobs

__all__ = [
    "SCHEDULER_ENV",
    "add_scheduler",
    "cluster",
    "cluster_jobs",
    "scheduler_address",
    "submit",
    "worker_model",
    "worker_path",
]

#: The environment variable read when ``--scheduler`` is not given.
SCHEDULER_ENV = "TIMEDEXEC_SCHEDULER"


def add_scheduler(parser: argparse.ArgumentParser, *, what: str = "the work") -> None:
    """Add ``--scheduler ADDRESS`` to ``parser``; ``what`` says what runs on the cluster."""
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help=f"run {what} on the Dask cluster whose scheduler is at ADDRESS (e.g. "
        f"tcp://10.0.0.5:8786; default: ${SCHEDULER_ENV} if set, else this machine; '' "
        "forces this machine); input files must be at the same path on every worker; "
        "needs the extra: python3 -m pip install 'timedexec[dask]'",
    )


def scheduler_address(args: argparse.Namespace) -> str | None:
    """The scheduler address of a command: ``--scheduler``, else ``$TIMEDEXEC_SCHEDULER``;
    None (this machine) when neither is set or the value is blank."""
    value = getattr(args, "scheduler", None)
    if value is None:
        value = os.environ.get(SCHEDULER_ENV)
    value = (value or "").strip()
    return value or None


@contextlib.contextmanager
def cluster(args: argparse.Namespace, command: str) -> Iterator[Any]:
    """Connect for the time of the block when the command has a scheduler address.

    Yields the ``distributed.Client`` (None on this machine). Inside, joblib runs on the
    cluster. A note on stderr names the cluster unless ``--quiet``.

    Raises
    ------
    ConfigError
        dask.distributed is not installed (the message says how to install the extra), or
        the workers run another timedexec.
    ConnectionError
        The scheduler does not answer or has no worker (exit 3).
    """
    address = scheduler_address(args)
    if address is None:
        yield None
        return
    from timedexec.fleet import on_cluster

    with on_cluster(address) as client:
        if not getattr(args, "quiet", False):
            workers = len(client.scheduler_info(n_workers=-1).get("workers", {}))
            note(command, f"running on the Dask cluster at {address} ({workers} worker(s))")
        yield client


def cluster_jobs(command: str, args: argparse.Namespace, client: Any) -> int:
    """The ``jobs`` to pass to the library: -1 (every worker) on a cluster, where an explicit
    ``--jobs`` is ignored with a note; else ``--jobs`` as :func:`used_jobs` caps it."""
    jobs = int(getattr(args, "jobs", 1))
    if client is None:
        return used_jobs(command, jobs)
    if jobs != 1 and not getattr(args, "quiet", False):
        note(
            command,
            f"--jobs {jobs} is ignored with --scheduler: every worker of the cluster is used",
        )
    return -1


def worker_path(path: str | os.PathLike[str], client: Any) -> str:
    """``path`` as workers must see it: absolute on a cluster (their working folder is not
    ours), as given on this machine."""
    return os.path.abspath(path) if client is not None else os.fspath(path)


def worker_model(model: str | None, client: Any) -> str | None:
    """A ``--model`` as workers must see it: a bundle folder absolute on a cluster; a
    shipped model's name (or None) as given."""
    if client is not None and model is not None and os.path.exists(model):
        return worker_path(model, client)
    return model


def submit(client: Any, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Any:
    """``fn(*args, **kwargs)``: as one task on the cluster (its exception re-raised here as
    it is), or in this process when ``client`` is None."""
    if client is None:
        return fn(*args, **kwargs)
    return client.submit(fn, *args, pure=False, **kwargs).result()
