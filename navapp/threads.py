"""BLAS / OpenMP thread limits that cost microseconds, not milliseconds.

``threadpoolctl.threadpool_limits`` scans every loaded shared library each time it is
entered (6.5 ms a call on this project's 2-core machine under load, measured side by side
against 0.01 ms for a kept controller): the LM loop enters one per registration and the
live re-registration one per frame, where a frame has 33 ms. A ``ThreadpoolController``
made once and kept does the scan once.

It is made again when modules were imported since (a new extension module may have brought
a thread pool of its own: under the two-worker test suite a second OpenBLAS, loaded after
the first limit, kept its two threads inside it); once the imports settle, no scan.
"""

import sys
import threading
from contextlib import contextmanager

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
