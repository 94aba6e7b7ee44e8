"""Where Monte Carlo work runs: this process or a Dask cluster (``--cluster``).

A Monte Carlo study cuts its work into independent tasks (the chunked TAN Monte Carlo: chunks
of whole seed blocks; the TAN and learned studies: one filter per method; the GNSS/INS study:
groups of variants). `open_cluster` gives a `Dispatcher` that runs them one after
the other in this process (``--cluster none``, the default of the small studies) or deals
them to a Dask cluster:

* ``local`` / ``local:N``: a `distributed.LocalCluster` of N worker processes of one
  thread each, started here and closed at the end (``local`` = the cores this process may
  use, `default_workers`);
* ``tcp://HOST:8786`` (any Dask scheduler address): joins a running scheduler (``dask
  scheduler`` and ``dask worker`` by hand, or a dask-jobqueue cluster on SLURM); the
  workers need the same neuralmap and torch installed.

A task is ``fn(shared, job)``: the inputs every task shares (world, tile, methods) are
scattered to the workers once, each job is small. Results come back in job order whatever
the order they finish in, and a task computes exactly what it computes in this process
(each task sets its own torch threads), so the results are bit-identical to one process
on the same machine. Progress comes from the cluster: each finished task is reported as it
completes (``as_completed``), and the waiting loop calls an idle callback so that progress
lines keep their heartbeat (`neuralmap.progress`). The dashboard address is printed.

Dask is optional: ``pip install 'neuralmap[dask]'``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Literal

from neuralmap.exceptions import NeuralMapError

__all__ = ["ClusterSpec", "Dispatcher", "default_workers", "open_cluster", "parse_cluster",
           "require_distributed"]

#: Scheduler address schemes Dask's comms understand.
_SCHEMES = ("tcp://", "tls://", "ucx://", "inproc://", "ws://", "wss://")
#: Seconds a ``tcp://`` scheduler has to answer before the run is refused.
CONNECT_TIMEOUT_S = 20.0
#: Seconds between two looks at the finished tasks (and idle callbacks) while waiting.
POLL_S = 0.2


@dataclass(frozen=True)
class ClusterSpec:
    """A parsed ``--cluster`` value.

    Attributes:
        kind: ``"process"`` (this process), ``"local"`` (a LocalCluster started here) or
            ``"scheduler"`` (a running scheduler joined at ``address``).
        workers: Worker processes of a LocalCluster (1 for ``process``; 0 = as many as the
            joined scheduler has).
        address: The scheduler address (``scheduler`` only).
    """

    kind: Literal["process", "local", "scheduler"]
    workers: int = 1
    address: str = ""

    def describe(self) -> str:
        """A short description for the log (``"this process"``, ``"local:4"``...)."""
        if self.kind == "process":
            return "this process"
        if self.kind == "local":
            return f"local:{self.workers}"
        return self.address


def default_workers() -> int:
    """Workers of ``--cluster local``: the CPU cores this process may run on (its affinity
    mask, else ``os.cpu_count()``), one single-threaded worker process per core."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux
        return max(1, os.cpu_count() or 1)


def parse_cluster(value: Any, *, option: str = "--cluster") -> ClusterSpec:
    """Parses a ``--cluster`` value.

    Args:
        value: ``None``/``"none"``/``"process"`` (this process), ``"local"``, ``"local:N"``
            or a scheduler address (``tcp://HOST:8786``); a `ClusterSpec` is returned
            as is.
        option: The option's name in messages.

    Returns:
        The `ClusterSpec`.

    Raises:
        NeuralMapError: Anything else, saying what is accepted.
    """
    if isinstance(value, ClusterSpec):
        return value
    if value is None:
        return ClusterSpec("process")
    if not isinstance(value, str):
        raise NeuralMapError(
            f"{option} {value!r}: expected a string: none, local, local:N or a Dask scheduler "
            "address such as tcp://HOST:8786.")
    text = value.strip()
    if text.lower() in ("", "none", "process"):
        return ClusterSpec("process")
    if text.lower() == "local":
        return ClusterSpec("local", workers=default_workers())
    if text.lower().startswith("local:"):
        count = text.split(":", 1)[1]
        if not count.isdigit() or int(count) < 1:
            raise NeuralMapError(
                f"{option} {value!r}: the worker count after 'local:' must be an integer >= 1 "
                "(e.g. local:4), or plain 'local' for one worker per core.")
        return ClusterSpec("local", workers=int(count))
    if text.startswith(_SCHEMES) and len(text.split("://", 1)[1]) > 0:
        return ClusterSpec("scheduler", workers=0, address=text)
    raise NeuralMapError(
        f"{option} {value!r}: expected none (this process), local (one worker per core), "
        "local:N (N local workers) or the address of a running Dask scheduler, such as "
        "tcp://HOST:8786.")


def require_distributed(what: str = "--cluster") -> Any:
    """Imports `distributed`; a clear error naming the extra when it is missing.

    Raises:
        NeuralMapError: Dask distributed is not installed.
    """
    try:
        import distributed
    except ImportError as exc:
        raise NeuralMapError(
            f"{what}: running on a Dask cluster needs Dask distributed, which is not "
            "installed. Install the dask extra (pip install 'neuralmap[dask]') or run in this "
            "process with --cluster none.") from exc
    return distributed


class Dispatcher:
    """Runs ``fn(shared, job)`` for every job, in this process or on a Dask client.

    Args:
        client: A `distributed.Client`, or None for this process.
        description: What it is, for the log.

    Attributes:
        client: The Dask client (None = this process).
        description: E.g. ``"this process"``, ``"LocalCluster of 4 workers"``.
    """

    def __init__(self, client: Any = None, description: str = "this process") -> None:
        self.client = client
        self.description = description

    @property
    def workers(self) -> int:
        """Task slots: 1 in this process, else the worker threads the scheduler knows now."""
        if self.client is None:
            return 1
        return max(1, int(sum(self.client.nthreads().values())))

    def map(
        self,
        fn: Callable[[Any, Any], Any],
        jobs: Sequence[Any],
        *,
        shared: Any = None,
        on_done: Callable[[int, Any], None] | None = None,
        on_idle: Callable[[], None] | None = None,
        name: str = "task",
    ) -> list[Any]:
        """Runs every job; returns the results in job order.

        Args:
            fn: A module-level function ``fn(shared, job) -> result`` (pickled by reference
                to the workers, which import it).
            jobs: The jobs (small, picklable).
            shared: What every task reads (scattered to every worker once).
            on_done: Called as ``on_done(index, result)`` when a task finishes (in the order
                they finish on a cluster).
            on_idle: Called about every `POLL_S` s while waiting for a cluster (a
                progress bar's ``update(0)`` keeps its heartbeat lines going).
            name: Prefix of the Dask task keys (shown on the dashboard).

        Returns:
            ``[fn(shared, job) for job in jobs]``.

        Raises:
            Whatever a task raised (the remaining tasks are cancelled).
        """
        if self.client is None:
            results = []
            for i, job in enumerate(jobs):
                out = fn(shared, job)
                results.append(out)
                if on_done is not None:
                    on_done(i, out)
            return results
        distributed = require_distributed()
        client = self.client
        [shared_future] = client.scatter([shared], broadcast=True, hash=False)
        stamp = f"{time.time_ns():x}"
        futures = [client.submit(fn, shared_future, job, pure=False, key=f"{name}-{stamp}-{i}")
                   for i, job in enumerate(jobs)]
        order = {future.key: i for i, future in enumerate(futures)}
        results: list[Any] = [None] * len(futures)
        pending = distributed.as_completed(futures)
        try:
            while not pending.is_empty():
                if not pending.has_ready():
                    if on_idle is not None:
                        on_idle()
                    time.sleep(POLL_S)
                    continue
                for future in pending.next_batch(block=False):
                    i = order[future.key]
                    results[i] = future.result()  # re-raises a task's exception here
                    future.release()
                    if on_done is not None:
                        on_done(i, results[i])
        except BaseException:
            client.cancel(futures)
            raise
        finally:
            client.cancel([shared_future])
        return results


@contextmanager
def open_cluster(
    cluster: Any = None,
    *,
    dashboard_address: str | None = ":8787",
    log: Callable[[str], None] | None = print,
) -> Iterator[Dispatcher]:
    """The `Dispatcher` of a ``--cluster`` value, open for the ``with`` block.

    Args:
        cluster: A ``--cluster`` value (`parse_cluster`), a `ClusterSpec`, or
            an open `distributed.Client` (used as is and left open).
        dashboard_address: Where a LocalCluster serves its dashboard (``":8787"``: that
            port, or a free one when taken; None = no dashboard, as in the tests).
        log: Where the cluster and dashboard lines go (None = silent).

    Yields:
        The dispatcher; a LocalCluster started here, or the connection to a scheduler, is
        closed when the block ends.

    Raises:
        NeuralMapError: Bad value, Dask not installed, or no scheduler at the address.
    """
    if cluster is not None and not isinstance(cluster, (str, ClusterSpec)):
        if not hasattr(cluster, "submit") or not hasattr(cluster, "scatter"):
            raise NeuralMapError(
                f"cluster {cluster!r}: expected none, local, local:N, a scheduler address or "
                "a distributed.Client.")
        address = getattr(getattr(cluster, "scheduler", None), "address", "") or "?"
        yield Dispatcher(cluster, f"the Dask scheduler at {address}")
        return
    spec = parse_cluster(cluster)
    if spec.kind == "process":
        yield Dispatcher(None)
        return
    distributed = require_distributed(f"--cluster {spec.describe()}")
    local = None
    if spec.kind == "local":
        local = distributed.LocalCluster(
            n_workers=spec.workers, threads_per_worker=1, processes=True,
            dashboard_address=dashboard_address)
        client = distributed.Client(local)
        description = f"a Dask LocalCluster of {spec.workers} worker(s), one thread each"
    else:
        try:
            client = distributed.Client(spec.address, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError) as exc:
            raise NeuralMapError(
                f"--cluster {spec.address}: no Dask scheduler answered within "
                f"{CONNECT_TIMEOUT_S:g} s ({exc}). Start one (dask scheduler, then dask worker "
                f"{spec.address} on each machine) or pass the address it prints.") from exc
        description = f"the Dask scheduler at {spec.address}"
    try:
        if log is not None:
            threads = int(sum(client.nthreads().values()))
            log(f"cluster: {description}; {threads} worker thread(s) now; "
                + _dashboard_text(client, local=local is not None,
                                  disabled=local is not None and dashboard_address is None))
            if not threads:
                log(f"cluster: the scheduler has no workers yet; the tasks wait for them "
                    f"(dask worker {spec.address})")
        yield Dispatcher(client, description)
    finally:
        client.close()
        if local is not None:
            local.close()


def _dashboard_text(client: Any, *, local: bool, disabled: bool) -> str:
    """``"dashboard http://HOST:PORT/status"``, or why there is none."""
    if disabled:
        return "no dashboard"
    if local:
        try:
            import bokeh  # noqa: F401  (a LocalCluster serves its dashboard only with it)
        except ImportError:
            return "no dashboard (pip install 'neuralmap[dask]' adds bokeh)"
    try:
        link = client.dashboard_link
    except (KeyError, AttributeError):
        link = ""
    return f"dashboard {link}" if link else "no dashboard"
