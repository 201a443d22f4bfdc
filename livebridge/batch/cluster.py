"""Jobs on a Dask ``distributed`` cluster: a :class:`distributed.LocalCluster` on this machine (worker processes,
scheduler and workers on 127.0.0.1 on free ports; the scheduler's HTTP routes (health, no dashboard) on a free
loopback port) or an existing scheduler.

Dask is an optional extra (``pip install 'livebridge[cluster]'``), imported only in this module. Workers send
each take's progress as events on a topic the client subscribes to (fire-and-forget: a slow client never
holds a worker up), at most every :data:`PROGRESS_EVERY_S`.
"""

from __future__ import annotations

import logging
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from urllib.parse import urlsplit

from livebridge.batch.jobs import TakeJob, TakeOutcome
from livebridge.batch.runner import OnDone, OnProgress, run_job
from livebridge.errors import InputError

EXTRA = "cluster"
PROGRESS_EVERY_S = 0.2
CONNECT_TIMEOUT_S = 10.0
SCHEMES = ("tcp", "tls")


def require_distributed():
    """The ``distributed`` module, or an :class:`InputError` naming the extra that installs it."""
    try:
        import distributed
    except ImportError:
        raise InputError("re-processing on a cluster needs Dask distributed, which is not installed: "
                         f"pip install 'livebridge[{EXTRA}]' (or use --workers 0 to process in this process)",
                         field="--scheduler/--workers") from None
    return distributed


def check_scheduler_address(address: str) -> str:
    """``tcp://HOST:PORT`` (or ``tls://``) with a port in 1-65535; :class:`InputError` naming ``--scheduler``."""
    parts = urlsplit(address)
    try:
        port = parts.port
    except ValueError:
        port = None
    if parts.scheme not in SCHEMES or not parts.hostname or port is None or not 1 <= port <= 65535 \
            or parts.path not in ("", "/") or parts.query:
        raise InputError(f"expected {' or '.join(s + '://HOST:PORT' for s in SCHEMES)}, got {address!r}",
                         field="--scheduler")
    return address


@contextmanager
def open_client(scheduler: str | None = None, workers: int = 2) -> Iterator:
    """A :class:`distributed.Client` of the scheduler at ``scheduler``, or of a new local cluster of ``workers``
    single-threaded worker processes bound to 127.0.0.1 (closed on exit)."""
    distributed = require_distributed()
    if scheduler is not None:
        check_scheduler_address(scheduler)
        try:
            client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError) as error:
            raise InputError(f"cannot reach the Dask scheduler at {scheduler} ({error})", field="--scheduler") from None
        with client:
            yield client
        return
    if workers < 1:
        raise InputError(f"a local cluster needs at least 1 worker, got {workers}", field="--workers")
    cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                                       scheduler_port=0, dashboard_address="127.0.0.1:0",
                                       scheduler_kwargs={"dashboard": False}, silence_logs=logging.ERROR)
    with cluster, distributed.Client(cluster) as client:
        yield client


def _job_on_worker(job: TakeJob, topic: str) -> TakeOutcome:
    """:func:`run_job` on a worker, its progress sent as events on ``topic``."""
    from distributed import get_worker

    worker, last = get_worker(), [0.0]

    def progress(done: int, total: int | None) -> None:
        now = time.monotonic()
        if now - last[0] >= PROGRESS_EVERY_S or done == total:
            last[0] = now
            worker.log_event(topic, (job.name, done, total))

    return run_job(job, progress)


def run_on_cluster(client, jobs: list[TakeJob], on_progress: OnProgress | None = None,
                   on_done: OnDone | None = None) -> list[TakeOutcome]:
    """Every job on the cluster of ``client``, as workers come free; outcomes in the jobs' order.

    A job that raises on its worker (a bug, not bad input: :func:`run_job` reports that) or whose worker dies
    is a failed outcome naming the error; the other jobs finish.
    """
    distributed = require_distributed()
    topic = f"livebridge-process-{uuid.uuid4().hex}"
    if on_progress is not None:
        client.subscribe_topic(topic, lambda event: on_progress(*event[1]))
    try:
        futures = client.map(_job_on_worker, jobs, [topic] * len(jobs), pure=False,
                             key=[f"process-{job.name}-{uuid.uuid4().hex[:8]}" for job in jobs])
        names = {future.key: job.name for future, job in zip(futures, jobs)}
        outcomes: dict[str, TakeOutcome] = {}
        for future in distributed.as_completed(futures):
            outcome = _outcome(future, names[future.key])
            outcomes[future.key] = outcome
            if on_done is not None:
                on_done(outcome)
        return [outcomes[future.key] for future in futures]
    finally:
        if on_progress is not None:
            client.unsubscribe_topic(topic)


def _outcome(future, name: str) -> TakeOutcome:
    if future.status == "finished":
        return future.result()
    error = future.exception()
    return TakeOutcome(name, False, reason=f"failed on its worker: {type(error).__name__}: {error}")
