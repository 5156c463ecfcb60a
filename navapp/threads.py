"""Threads: BLAS / OpenMP limits that cost microseconds, not milliseconds (``limit_threads``),
independent tasks on the machine's cores (``in_threads``), and the compiled kernels split among
threads for the live update (``split_kernels``, ``both``).

``threadpoolctl.threadpool_limits`` scans every loaded shared library each time it is
entered (6.5 ms a call on this project's 2-core machine under load, measured side by side
against 0.01 ms for a kept controller): the LM loop enters one per registration and the
live re-registration one per frame, where a frame has 33 ms. A ``ThreadpoolController``
made once and kept does the scan once.

It is made again when modules were imported since (a new extension module may have brought
a thread pool of its own: under the two-worker test suite a second OpenBLAS, loaded after
the first limit, kept its two threads inside it); once the imports settle, no scan.

A split kernel computes each point as on one thread, so its answers are the same bits; it
pays only where the machine runs the second thread at once (``registration.live.SecondCore``
chooses per update).
"""

import multiprocessing
import os
import sys
import threading
import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, wait
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


def _kept_pool() -> ThreadPoolExecutor:
    """The one helper thread kept between calls, for ``in_threads``' tasks and ``both``'s second
    half: a caller whose work it has not begun takes that work back."""
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="navapp-helper")
        return _pool


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


def in_threads(task: Callable[[int], T], count: int, threads: int | None = None,
               lead: Callable[[], None] | None = None) -> list[T]:
    """``[task(0), …, task(count − 1)]``, the tasks taken in index order by ``threads`` threads
    (default ``task_threads()``): this one and a helper kept between calls. ``lead``: the
    caller's own work, independent of the tasks, run on this thread before it takes any (the
    helper begins with them meanwhile; on one thread, before the first): a task that needs
    what ``lead`` makes waits for it (``support.check_support_pair``'s ``beside``).

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
            if lead is not None:
                lead()
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

    pool = _kept_pool()
    with warnings.catch_warnings(), limit_threads(1):
        helper = pool.submit(drain) if threads > 1 else None
        if lead is not None:
            try:
                lead()
            except BaseException as e:  # no task is taken after it; raised below
                with lock:
                    failed.insert(0, e)
        drain()
        if helper is not None and not helper.cancel():  # cancelled: it never started (the helper was busy)
            helper.result()
    if failed:
        raise failed[0]
    return out


# --- compiled kernels split among threads (the live update's second core) ---------------------

_split = threading.local()  # this thread's kernel threads (``split_kernels``)
SPLIT_MIN = 64  # a kernel over fewer points (or triangles) stays on the calling thread
_layer: list = []  # [True] once Numba's TBB layer is up, [False] where it cannot be loaded


def kernel_threads() -> int:
    """How many threads the compiled per-point kernels may split one call among in this thread:
    1 (each kernel on the calling thread) unless inside ``split_kernels``."""
    return getattr(_split, "n", 1)


def _tbb() -> bool:
    """Numba's parallel kernels run on its TBB layer or not at all. TBB's threads take chunks
    as they come free, so a thread the machine does not run holds back only the chunk it took;
    OpenMP's barrier waits for every thread (a live update's search and α columns took 13–59 ms
    on this 2-core machine under load, against 1.7–1.9 ms on one thread; docs/decisions/speed.md,
    "The live update on two cores"). TBB is also safe under fork and from several threads.
    Where it cannot be loaded the kernels stay serial."""
    if not _layer:
        try:
            import numba
            from numba.np.ufunc import parallel

            if not parallel._is_initialized:
                numba.config.THREADING_LAYER = "tbb"
            try:
                parallel._launch_threads()
            except ValueError:  # no TBB: Numba's own choice for anything else that asks
                numba.config.THREADING_LAYER = "default"
                raise
            _layer.append(numba.threading_layer() == "tbb")
        except (ImportError, ValueError):
            _layer.append(False)
    return _layer[0]


@contextmanager
def split_kernels(threads: int | None = 2):
    """Within it, the compiled per-point kernels of registration that are worth it (the
    surfaces' closest points, the Jacobian's α columns; ≥ ``SPLIT_MIN`` points) split a call's
    points among ``threads`` threads of Numba's TBB pool (None: the machine's cores), and eq. 8's
    product its rows between two (``both``), in this thread only. Each point (row) is computed
    as on one thread, so the answers are the same bits. Where TBB cannot be loaded, or at one
    thread, nothing is split."""
    held = kernel_threads()
    n = 1
    if threads is None or threads > 1:
        if _tbb():
            import numba

            n = numba.config.NUMBA_NUM_THREADS if threads is None else min(threads, numba.config.NUMBA_NUM_THREADS)
    if n <= 1:
        _split.n = 1
        try:
            yield
        finally:
            _split.n = held
        return
    import numba

    threads_before, chunk_before = numba.get_num_threads(), numba.get_parallel_chunksize()
    numba.set_num_threads(n)
    # one loop iteration (``compiled.CHUNK`` points) a task, taken by whichever thread is
    # free: Numba's default cuts the loop into one piece a thread up front
    numba.set_parallel_chunksize(1)
    _split.n = n
    try:
        yield
    finally:
        _split.n = held
        numba.set_num_threads(threads_before)
        numba.set_parallel_chunksize(chunk_before)


def both(first, second) -> None:
    """Run ``first()`` on this thread and ``second()`` beside it on a helper thread, inside
    ``split_kernels`` with two threads or more (else both here, in turn); returns when both
    are done. ``second`` is taken back and run here if the helper has not begun it by the time
    ``first`` ends, so a helper the machine does not run costs nothing but the hand-over.
    For NumPy calls that release the GIL (BLAS), each on its own rows of the answer."""
    if kernel_threads() < 2:
        first()
        second()
        return
    future = _kept_pool().submit(second)
    try:
        first()
    finally:  # the helper never writes into the answer after this returns
        taken_back = future.cancel()
        if not taken_back:
            wait([future])
    if taken_back:
        second()
    elif (failed := future.exception()) is not None:
        raise failed
