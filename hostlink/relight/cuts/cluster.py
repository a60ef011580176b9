"""The cut precompute on a Dask cluster (``dask.distributed``).

The SVC / VCF precompute is embarrassingly parallel: :func:`lightprobe.hostlink.relight.cuts.precompute.run_chunk`
is a pure function of (scene key, chunk range, parameters). Here each missing chunk becomes one
Dask task; the scene's meshes and normals (a :class:`~lightprobe.hostlink.relight.cuts.precompute.Job`) are
scattered once to every worker (``broadcast=True``), so a task carries only its 4-tuple, and each
worker builds each Embree scene once (the per-process table in ``precompute``). Results come back
as they finish (``as_completed``) and the caller caches each one at once, so:

* a worker that dies mid-run costs only its running tasks, which the scheduler reruns elsewhere
  (the job stays on the surviving workers; a restarted worker fetches it from a peer);
* a client that dies mid-run (or a scheduler lost) leaves the finished chunks on disk, and the
  next run submits only the missing ones.

``cluster`` is a ``distributed.Client``, a scheduler address (``tcp://host:8786``; or the
``DASK_SCHEDULER_ADDRESS`` environment variable via :func:`resolve`) or ``"local"``: a
``LocalCluster`` of one single-threaded worker process per core (Embree's threads inside a task
would only fight the other workers for the same cores).

Worker memory: Dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_=65536``
(``distributed.nanny.pre-spawn-environ``), which also freezes glibc's mmap threshold at 128 KiB:
every large temporary of a chunk is then a fresh ``mmap`` and page faults. Measured here, an SVC
chunk costs 1.6x its time in a plain process (4 chunks: 2.9 s against 1.8 s). The local cluster
is started without that variable; for a remote cluster start the workers without it too
(``DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON='{"OMP_NUM_THREADS": 1}'`` or a config file).
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from lightprobe.core.errors import InputError

__all__ = ["ENV_ADDRESS", "connect", "resolve", "run_on_dask"]

log = logging.getLogger(__name__)

ENV_ADDRESS = "DASK_SCHEDULER_ADDRESS"
# the nanny's default without MALLOC_TRIM_THRESHOLD_ (see the module doc)
SPAWN_ENV = {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1}


def resolve(flag: str | None) -> str | None:
    """What ``--precompute-on`` means: the flag, else ``$DASK_SCHEDULER_ADDRESS``, else ``None``
    (in-process). Checks the form: ``local`` or ``tcp://HOST:PORT`` (also ``tls://``,
    ``inproc://``)."""
    value = flag if flag is not None else os.environ.get(ENV_ADDRESS) or None
    if value is None or value == "local":
        return value
    scheme, sep, rest = value.partition("://")
    if not sep or scheme not in ("tcp", "tls", "inproc", "ucx", "ws", "wss") or not rest:
        where = "--precompute-on" if flag is not None else ENV_ADDRESS
        raise InputError(f"{where} must be 'local' or a scheduler address such as "
                         f"tcp://HOST:8786, got {value[:80]!r}", param=where)
    return value


@contextlib.contextmanager
def connect(cluster: Any, *, workers: int | None = None, timeout: float = 10.0) -> Iterator[Any]:
    """A ``distributed.Client`` for ``cluster`` (see the module doc); closes what it opened."""
    from distributed import Client, LocalCluster

    if isinstance(cluster, Client):
        yield cluster
        return
    if cluster == "local":
        import dask

        n = workers or os.cpu_count() or 1
        with dask.config.set({"distributed.nanny.pre-spawn-environ": SPAWN_ENV}), \
                LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                             dashboard_address=None) as lc, Client(lc) as client:
            yield client
        return
    try:
        client = Client(str(cluster), timeout=timeout)
    except (OSError, TimeoutError) as e:
        raise InputError(f"cannot reach the Dask scheduler at {cluster}: {e}",
                         param="--precompute-on") from e
    try:
        yield client
    finally:
        client.close()


def run_on_dask(fn: Callable[[Any, tuple[str, int, int, int]], Any], job: Any,
                chunks: Sequence[tuple[str, int, int, int]], cluster: Any,
                done: Callable[[tuple[str, int, int, int], Any], None]) -> None:
    """Run ``fn(job, chunk)`` for each of ``chunks`` as Dask tasks (``job`` is a dataclass with
    ``key`` and ``threads``); call ``done(chunk, result)`` (in this thread) as each finishes.
    Tasks are keyed by (job key, chunk), so two clients of one scheduler precomputing the same
    scene share the work."""
    import dataclasses

    from distributed import as_completed

    if not chunks:
        return
    with connect(cluster) as client:
        # one Embree thread per task: the workers are the parallelism
        remote = dataclasses.replace(job, threads=1)
        shipped = client.scatter(remote, broadcast=True, hash=False)
        futures = {client.submit(fn, shipped, c, key=f"lightprobe-cut-{job.key}-{'-'.join(map(str, c))}",
                                 retries=3): c for c in chunks}
        for fut in as_completed(futures):
            done(futures[fut], fut.result())
        log.info("precompute: %d chunks on %d Dask workers", len(chunks),
                 len(client.scheduler_info().get("workers", {})))
