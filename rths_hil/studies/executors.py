"""Executors the studies run their cases through.

All studies run their cases through an executor (default
``concurrent.futures.ProcessPoolExecutor(max_workers=2)``); any
:class:`concurrent.futures.Executor` can be passed, e.g. a Dask one from :func:`open_executor`
(a ``LocalCluster`` on 127.0.0.1 or a lab's scheduler). Progress goes to stderr through tqdm.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import re
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor, as_completed

from tqdm import tqdm

from ..errors import InputError, require

log = logging.getLogger(__name__)


class SerialExecutor(Executor):
    """Runs each task in the calling process at submit time (for tests and ``--workers 1``)."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        fut: Future = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except Exception as exc:  # delivered through the future, like a pool
            fut.set_exception(exc)
        return fut


def make_executor(workers: int) -> Executor:
    """``SerialExecutor`` for 1 worker, else ``ProcessPoolExecutor(max_workers=workers)``."""
    if int(workers) != workers or workers < 1:
        raise InputError(f"workers must be a positive integer, got {workers!r}")
    if workers == 1:
        return SerialExecutor()
    return ProcessPoolExecutor(max_workers=int(workers), initializer=_worker_signals)


def _default_executor() -> Executor:
    return ProcessPoolExecutor(max_workers=2, initializer=_worker_signals)


def _worker_signals() -> None:
    """In a pool's worker: Ctrl-C in the terminal reaches the whole process group; the study's
    own process stops the work (:func:`stop_pool`), so the workers do not take it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def stop_pool(ex: Executor) -> None:
    """After an operator stop: cancel what has not started and end a process pool's workers
    at once (the trials under way are lost; those finished were delivered)."""
    if not isinstance(ex, ProcessPoolExecutor):  # a Dask executor cancels what runs
        with contextlib.suppress(Exception):
            ex.shutdown(wait=False)
        return
    ex.shutdown(wait=False, cancel_futures=True)
    if isinstance(ex, ProcessPoolExecutor):
        for child in multiprocessing.active_children():
            child.terminate()
        for child in multiprocessing.active_children():
            child.join(5)


def run_cases(
    func,
    cases: Sequence[tuple],
    executor: Executor | None,
    progress: bool,
    desc: str,
    on_result=None,
):
    """Submit ``func(*case)`` for each case; return results in case order.

    ``on_result(index, result)`` is called as each case completes (in completion order).
    """

    own = executor is None
    ex: Executor = _default_executor() if executor is None else executor
    results: list = [None] * len(cases)
    if isinstance(ex, SerialExecutor):  # one at a time here: each delivered as it finishes
        with tqdm(total=len(cases), desc=desc, file=sys.stderr, disable=not progress) as bar:
            for i, case in enumerate(cases):
                results[i] = func(*case)
                if on_result is not None:
                    on_result(i, results[i])
                bar.update(1)
        return results
    stopped = False
    try:
        futures = {ex.submit(func, *case): i for i, case in enumerate(cases)}
        bar = tqdm(total=len(cases), desc=desc, file=sys.stderr, disable=not progress, unit="case")
        with bar:
            for fut in as_completed(futures):
                results[futures[fut]] = fut.result()
                if on_result is not None:
                    on_result(futures[fut], results[futures[fut]])
                bar.update(1)
    except KeyboardInterrupt:  # an operator stop (rths_hil.stopping.interrupting)
        stopped = True
        stop_pool(ex)
        raise
    finally:
        if own and not stopped:
            ex.shutdown(wait=True, cancel_futures=True)
    return results


# --------------------------------------------------------------------------------------------
# executors: local processes, a local Dask cluster or a lab's Dask scheduler


@contextlib.contextmanager
def open_executor(scheduler: str | None = None, workers: int = 2) -> Iterator[Executor]:
    """An executor for the studies, closed (with its cluster) on exit.

    Parameters
    ----------
    scheduler : str, optional
        ``None``: :func:`make_executor` (in-process for 1 worker, else a process pool).
        ``"local"``: a ``dask.distributed.LocalCluster`` of ``workers`` single-threaded worker
        processes, scheduler and workers bound to 127.0.0.1 over TCP. Anything else is the
        address of a running Dask scheduler (``tcp://host:8786``; ``host:8786`` means TCP),
        e.g. a lab's cluster started with ``dask scheduler`` and ``dask worker --nthreads 1``.
    workers : int
        Worker processes of a local pool or cluster (ignored with an address).

    Yields
    ------
    concurrent.futures.Executor
        For Dask, ``Client.get_executor(pure=False)``: every submitted task runs, and a task
        whose worker dies is rerun on another one (the scheduler's ``allowed-failures``).
    """
    if scheduler is None:
        pool = make_executor(workers)
        with _serving(pool, lambda: pool.shutdown(wait=True, cancel_futures=True)) as ex:
            yield ex
        return
    if int(workers) != workers or workers < 1:
        raise InputError(f"workers must be a positive integer, got {workers!r}")

    require("studies", "a Dask scheduler (--scheduler, study robustness)")
    from distributed import Client, LocalCluster

    if logging.getLogger().getEffectiveLevel() > logging.INFO:
        logging.getLogger("distributed").setLevel(logging.WARNING)  # no start/stop chatter
    cluster = None
    if scheduler == "local":
        cluster = LocalCluster(
            n_workers=int(workers),
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            protocol="tcp",
            dashboard_address=None,
        )
        client = Client(cluster)
        client.wait_for_workers(int(workers))
    else:
        address = scheduler if "://" in scheduler else f"tcp://{scheduler}"
        if not _ADDRESS_RE.match(address):
            raise InputError(
                f"--scheduler {scheduler!r}: expected 'local' or a scheduler address with its "
                "port, such as tcp://host:8786"
            )
        _probe_scheduler(address, scheduler)
        try:
            client = Client(address, timeout=10)
        except (OSError, TimeoutError) as exc:
            raise InputError(
                f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc})"
            ) from None
        n = len(client.scheduler_info().get("workers", {}))
        log.info("Dask scheduler %s with %d worker(s)", address, n)
        if n == 0:
            log.warning("the Dask scheduler at %s has no workers yet; tasks will wait", address)

    def close() -> None:
        client.close()
        if cluster is not None:
            cluster.close()

    with _serving(client.get_executor(pure=False), close) as ex:
        yield ex


@contextlib.contextmanager
def _serving(ex: Executor, close: Callable[[], None]) -> Iterator[Executor]:
    """``ex``, its tasks stopped at an operator stop (KeyboardInterrupt); ``close()`` on exit."""
    try:
        yield ex
    except KeyboardInterrupt:
        stop_pool(ex)
        raise
    finally:
        close()


_ADDRESS_RE = re.compile(r"^(tcp|tls|inproc|ucx|ws|wss)://[^\s/:]+:\d+/?$")
#: How long a scheduler address has to answer distributed's connection handshake (s).
HANDSHAKE_TIMEOUT = 15.0


def _probe_scheduler(address: str, given: str) -> None:
    """Refuse an address where no Dask scheduler answers distributed's own handshake in
    :data:`HANDSHAKE_TIMEOUT` seconds. ``Client(address, timeout=...)`` bounds the TCP connect
    but not the handshake that follows it: a port where something else listens and keeps the
    connection open (a web server, a twin) would hold it for ever."""
    import asyncio

    from distributed.comm import connect

    async def probe() -> None:
        comm = await asyncio.wait_for(connect(address, timeout=10), HANDSHAKE_TIMEOUT)
        await comm.close()

    try:
        asyncio.run(probe())
    except TimeoutError:
        raise InputError(
            f"--scheduler {given}: no Dask scheduler answered at {address} within "
            f"{HANDSHAKE_TIMEOUT:g} s (something else listens there?)"
        ) from None
    except (OSError, ValueError) as exc:
        raise InputError(f"--scheduler {given}: cannot reach the Dask scheduler ({exc})") from None
