"""BLAS / OpenMP thread limits that cost microseconds, not milliseconds; independent tasks
on the machine's cores.

``threadpoolctl.threadpool_limits`` scans every loaded shared library each time it is
entered (6.5 ms a call on this project's 2-core machine under load, measured side by side
against 0.01 ms for a kept controller): the LM loop enters one per registration and the
live re-registration one per frame, where a frame has 33 ms. A ``ThreadpoolController``
made once and kept does the scan once.

It is made again when modules were imported since (a new extension module may have brought
a thread pool of its own: under the two-worker test suite a second OpenBLAS, loaded after
the first limit, kept its two threads inside it); once the imports settle, no scan.
"""

import multiprocessing
import os
import sys
import threading
import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

from threadpoolctl import ThreadpoolController

_controller: ThreadpoolController | None = None
_modules = -1  # len(sys.modules) when it was made
_held = threading.local()  # the limits this thread is inside, innermost last


def limit_threads(limits: int = 1):
    """A context manager holding the BLAS / OpenMP pools at ``limits`` threads.

    Inside a limit of the same count entered by the same thread it does nothing: the outer
    one holds the pools until after it ends (a live update entered four a frame, 0.1–0.2 ms
    each: the update's, LM's and the k-d queries' of the centerlines)."""
    global _controller, _modules
    held = getattr(_held, "limits", None)
    if held is None:
        held = _held.limits = []
    if held and held[-1] == limits:
        return _nested(held, limits)
    if _controller is None or len(sys.modules) != _modules:
        _controller, _modules = ThreadpoolController(), len(sys.modules)
    return _entered(held, limits, _controller.limit(limits=limits))


@contextmanager
def _nested(held, limits):
    held.append(limits)
    try:
        yield
    finally:
        held.pop()


@contextmanager
def _entered(held, limits, limiter):
    held.append(limits)
    try:
        with limiter:
            yield
    finally:
        held.pop()


T = TypeVar("T")
_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()
_inside = threading.local()  # ``task``: this thread is running ``in_threads`` tasks


def task_threads() -> int:
    """How many threads ``in_threads`` runs tasks on: the cores this process may use, at most
    two, and one in a worker process of a pool (a study's ``--workers``, a Dask worker),
    whose siblings already fill the cores (docs/decisions/speed.md, "The folds on both cores")."""
    if multiprocessing.parent_process() is not None:
        return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(2, cores))


def in_threads(task: Callable[[int], T], count: int, threads: int | None = None) -> list[T]:
    """``[task(0), …, task(count − 1)]``, the tasks taken in index order by ``threads`` threads
    (default ``task_threads()``): this one and a helper kept between calls.

    For tasks whose heavy parts release the GIL (Numba's ``nogil`` kernels, BLAS, LAPACK) and
    that share no state a task writes to but through whole replacements (``ModelCache``): each
    result is the one ``task`` gives alone, and they come back in index order. BLAS and OpenMP
    are held at one thread in every task (two tasks' threaded BLAS on two cores only wait on
    each other), and the warning filters are restored after them (``warnings.catch_warnings``
    entered by tasks in two threads at once can leave one's filter in place). Called from a
    task, or while the helper is busy with another caller's tasks, this thread takes them all.
    A task's exception is raised here, after every thread has stopped taking tasks."""
    threads = task_threads() if threads is None else threads
    if threads <= 1 or count <= 1 or getattr(_inside, "task", False):
        with limit_threads(1):
            return [task(i) for i in range(count)]
    out: list = [None] * count
    lock = threading.Lock()
    order = iter(range(count))
    failed: list[BaseException] = []

    def drain() -> None:
        _inside.task = True
        try:
            with limit_threads(1):  # OpenMP's limit is the calling thread's own
                while True:
                    with lock:
                        i = None if failed else next(order, None)
                    if i is None:
                        return
                    try:
                        out[i] = task(i)
                    except BaseException as e:  # raised in the caller's thread below
                        with lock:
                            failed.append(e)
                        return
        finally:
            _inside.task = False

    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="navapp-task")
        pool = _pool
    with warnings.catch_warnings(), limit_threads(1):
        helper = pool.submit(drain) if threads > 1 else None
        drain()
        if helper is not None and not helper.cancel():  # cancelled: it never started (the helper was busy)
            helper.result()
    if failed:
        raise failed[0]
    return out
