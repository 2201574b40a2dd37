"""Batch measuring on a Dask cluster: ``dbh measure --scheduler ADDRESS``.

:func:`iter_cluster_results` connects a ``distributed.Client`` to an existing scheduler, sends
the batch's :class:`~.batch.Job` objects to its workers and yields their
:class:`~monodbh.toolkit.result.MeasureResult` rows in input order as they come back, so the
caller writes them into the same CSV, JSON lines, GeoJSON and report as a local run
(:class:`~.outputs.results_file.ResultWriter`).

On a worker, :func:`run_on_worker` creates the backend's measure function and
:class:`~monodbh.toolkit.pipeline.Session` (the models) once per worker process, on its first
job, and measures with :func:`~.batch.run_job`, exactly as a local run does; jobs of one process
run one at a time on its session (onnxruntime already uses the cores; start workers with
``--nthreads 1`` and as many processes as the machine has cores / 2). A session that cannot be
created stops the batch with one :class:`~.batch.BatchError`, like a local run; a worker that
dies turns its photo into an error row and the batch goes on.

Requirements: ``pip install monodbh[cluster]`` here and on every worker (the same version),
and the photos, the ``--out-dir`` and any ``--models-dir`` at the same paths on every worker
(a shared file system). At most :func:`window` jobs are in flight at once, so tens of thousands
of photos do not pile up in the scheduler's memory.

Imported by :func:`monodbh.toolkit.batch.iter_results` only when a scheduler is given; imports
``distributed`` there and then.
"""
from __future__ import annotations

import threading
import uuid
from collections import deque
from typing import Iterator, Sequence

from .batch import Backend, BatchError, Job, error_result, one_line, run_job
from .result import MeasureResult

__all__ = ["iter_cluster_results", "run_on_worker", "window", "CONNECT_TIMEOUT_S"]

#: seconds to wait for the scheduler before giving up
CONNECT_TIMEOUT_S = 20

#: Backend -> ("ok", fn, session, lock) or ("fatal", message), per worker process
_CACHE: dict[Backend, tuple] = {}
_CACHE_LOCK = threading.Lock()


def _worker_state(backend: Backend) -> tuple:
    with _CACHE_LOCK:
        state = _CACHE.get(backend)
        if state is None:
            try:
                state = ("ok", backend.function(), backend.new_session(), threading.Lock())
            except Exception as exc:  # noqa: BLE001 - reported once, raised in the client
                from monodbh.calib.errors import MonodbhError

                state = ("fatal", f"{exc}" if isinstance(exc, MonodbhError)
                         else f"{type(exc).__name__}: {one_line(exc)}")
            _CACHE[backend] = state
    return state


def run_on_worker(job: Job, backend: Backend) -> MeasureResult | tuple[str, str]:
    """Measure one job on a Dask worker (:func:`~.batch.run_job` with the process's session).

    Returns
    -------
    MeasureResult, or ``("fatal", message)`` when the function or session cannot be set up.
    """
    state = _worker_state(backend)
    if state[0] == "fatal":
        return state
    _, fn, session, lock = state
    with lock:
        return run_job(job, fn, session)


def window(total_threads: int) -> int:
    """Jobs kept in flight on a cluster of ``total_threads`` worker threads."""
    return max(8, 4 * int(total_threads))


def _connect(address: str):
    try:
        from distributed import Client
    except ImportError:
        raise BatchError("--scheduler needs Dask's distributed package: pip install monodbh[cluster]") from None
    try:
        return Client(address, timeout=f"{CONNECT_TIMEOUT_S}s", set_as_default=False)
    except Exception as exc:  # noqa: BLE001 - OSError, TimeoutError, ValueError on a bad address
        raise BatchError(f"cannot reach the Dask scheduler at {address} ({type(exc).__name__}: "
                         f"{one_line(exc)})") from None


def iter_cluster_results(jobs: Sequence[Job], backend: Backend, address: str) -> Iterator[MeasureResult]:
    """Measure ``jobs`` on the Dask cluster at ``address``; yield the rows in input order.

    Parameters
    ----------
    jobs : sequence of Job
        Photo paths and ``out_dir`` must be valid on the workers.
    backend : Backend
        Measure function and session factory (created once per worker process).
    address : str
        The scheduler, e.g. ``"tcp://10.0.0.5:8786"``.

    Raises
    ------
    BatchError
        The scheduler cannot be reached, has no workers, or the workers cannot set up the
        measure function or its session.
    """
    jobs = list(jobs)
    if not jobs:
        return
    client = _connect(address)
    pending: deque = deque()
    try:
        try:
            client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
        except Exception:  # noqa: BLE001 - TimeoutError
            raise BatchError(f"the Dask scheduler at {address} has no workers") from None
        depth = window(sum(client.nthreads().values()) or 1)
        run_id = uuid.uuid4().hex[:8]
        todo = iter(jobs)

        def submit() -> None:
            job = next(todo, None)
            if job is not None:
                pending.append((job, client.submit(run_on_worker, job, backend, pure=False,
                                                   key=f"monodbh-measure-{run_id}-{job.index}")))

        for _ in range(depth):
            submit()
        while pending:
            job, fut = pending.popleft()
            try:
                res = fut.result()
            except Exception as exc:  # noqa: BLE001 - KilledWorker, a result that did not unpickle
                res = error_result(job.photo, f"{job.photo}: internal error on the Dask cluster: "
                                              f"{type(exc).__name__}: {one_line(exc)}")
            fut.release()
            if isinstance(res, tuple):
                raise BatchError(res[1])
            submit()
            yield res
    finally:
        for _, fut in pending:
            fut.cancel()
        client.close()
