"""Where a fleet's per-log work runs: in this process, in a pool of processes, or on Ray.

Every backend maps one top-level function ``fn(common, item)`` over the items and hands the
results back in the items' order, whatever order they finished in; ``common`` (the profile,
a Q-table) goes to each worker once, not with every item. A worker that dies takes only its
own items with it: they come back as ``WorkerLost``, and the caller reports them as failed.

* ``serial``  — this process, one item after another (``--workers 1``, the default);
* ``pool``    — ``--workers N``: N processes from a fork server that imported the evaluator
                once (each worker starts warm), each loading a detector once for all its logs;
* ``ray``     — ``--address local`` starts a Ray instance on this machine with N CPUs,
                ``--address auto|HOST:PORT|ray://HOST:PORT`` joins a cluster; one task per item,
                at most N in flight (the ``fleet`` extra; the daemon never imports Ray).
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, Protocol

from respecd.errors import InputError
from respecd.lab.fleet import worker
from respecd.perception.stage import share_detectors

OnDone = Callable[[int, Any], None]
RAY_OBJECT_STORE_BYTES = 256 * 1024 * 1024  # a local instance: results are small, the default takes 30 % of RAM


@dataclass(frozen=True)
class WorkerLost:
    """An item whose worker died (killed, out of memory) before it answered."""

    reason: str


class Backend(Protocol):
    kind: str
    workers: int
    startup_s: float  # seconds it took to get the backend up (processes, a Ray instance)

    def map(self, fn: Callable[[Any, Any], Any], common: Any, items: Sequence[Any],
            on_done: OnDone | None = None) -> list[Any]: ...

    def close(self) -> None: ...


def open_backend(workers: int, address: str | None, settings: worker.Settings) -> Backend:
    """The backend ``--workers`` and ``--address`` ask for (InputError: Ray missing or unreachable)."""
    if address is not None:
        return RayBackend(workers, address, settings)
    if workers <= 1:
        return SerialBackend(settings)
    return PoolBackend(workers, settings)


class SerialBackend:
    """This process, in order."""

    kind = "serial"
    workers = 1

    def __init__(self, settings: worker.Settings) -> None:
        start = time.perf_counter()
        self._sharing = share_detectors()  # each checkpoint loaded once while the backend is open
        self._sharing.__enter__()
        self.startup_s = time.perf_counter() - start

    def map(self, fn: Callable[[Any, Any], Any], common: Any, items: Sequence[Any],
            on_done: OnDone | None = None) -> list[Any]:
        results = []
        for i, item in enumerate(items):
            results.append(fn(common, item))
            if on_done is not None:
                on_done(i, results[-1])
        return results

    def close(self) -> None:
        self._sharing.__exit__(None, None, None)


class PoolBackend:
    """``workers`` processes forked from a server that imported the evaluator."""

    kind = "pool"

    def __init__(self, workers: int, settings: worker.Settings) -> None:
        start = time.perf_counter()
        self.workers = workers
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload(["respecd.lab.fleet.worker"])  # torch and respecd once, before the forks
        self._pool = ProcessPoolExecutor(workers, mp_context=context, initializer=worker.start, initargs=(settings,))
        self.startup_s = time.perf_counter() - start

    def map(self, fn: Callable[[Any, Any], Any], common: Any, items: Sequence[Any],
            on_done: OnDone | None = None) -> list[Any]:
        results: list[Any] = [None] * len(items)
        futures: dict[Future[Any], int] = {}
        try:
            futures = {self._pool.submit(fn, common, item): i for i, item in enumerate(items)}
        except BrokenProcessPool as err:
            raise InputError(f"--workers: the process pool could not start: {err}") from err
        pending = set(futures)
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in sorted(done, key=futures.__getitem__):
                i = futures[future]
                try:
                    results[i] = future.result()
                except BrokenProcessPool as err:
                    results[i] = WorkerLost(f"its worker process died ({err})")
                if on_done is not None:
                    on_done(i, results[i])
        return results

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class RayBackend:
    """One Ray task per item, at most ``workers`` in flight."""

    kind = "ray"

    def __init__(self, workers: int, address: str, settings: worker.Settings) -> None:
        try:
            import ray
        except ImportError as err:
            raise InputError("--address: Ray is not installed (pip install 'respecd[fleet]')") from err
        start = time.perf_counter()
        self._ray = ray
        self.workers = max(workers, 1)
        self.settings = settings
        options: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False, "configure_logging": False}
        if address == "local":
            options.update(num_cpus=self.workers, object_store_memory=RAY_OBJECT_STORE_BYTES)
        else:
            options["address"] = address
        if ray.is_initialized():
            ray.shutdown()
        try:
            ray.init(**options)
        except (ConnectionError, ValueError, RuntimeError) as err:
            raise InputError(f"--address {address}: cannot start or join Ray: {err}") from err
        self.address = address
        self.startup_s = time.perf_counter() - start

    def map(self, fn: Callable[[Any, Any], Any], common: Any, items: Sequence[Any],
            on_done: OnDone | None = None) -> list[Any]:
        ray = self._ray
        task = ray.remote(num_cpus=1, max_retries=0)(_on_ray)
        shared = ray.put((self.settings, fn, common))
        results: list[Any] = [None] * len(items)
        queue = list(enumerate(items))
        running: dict[Any, int] = {}
        while queue or running:
            while queue and len(running) < self.workers:
                i, item = queue.pop(0)
                running[task.remote(shared, item)] = i
            done, _ = ray.wait(list(running), num_returns=1)
            for ref in done:
                i = running.pop(ref)
                try:
                    results[i] = ray.get(ref)
                except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError,
                        ray.exceptions.RayTaskError) as err:
                    results[i] = WorkerLost(f"its Ray task failed ({type(err).__name__}: {str(err)[:200]})")
                if on_done is not None:
                    on_done(i, results[i])
        return results

    def close(self) -> None:
        self._ray.shutdown()


def _on_ray(shared: tuple[worker.Settings, Callable[[Any, Any], Any], Any], item: Any) -> Any:
    """A Ray task: the worker set up once per process, then ``fn(common, item)``."""
    settings, fn, common = shared
    worker.start(settings)
    return fn(common, item)

