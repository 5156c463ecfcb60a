"""BLAS / OpenMP thread limits that cost microseconds, not milliseconds.

``threadpoolctl.threadpool_limits`` scans every loaded shared library each time it is
entered (6.5 ms a call on this project's 2-core machine under load, measured side by side
against 0.01 ms for a kept controller): the LM loop enters one per registration and the
live re-registration one per frame, where a frame has 33 ms. A ``ThreadpoolController``
made once and kept does the scan once.

The controller is made at the first call, so thread pools of libraries loaded later are
not limited by it; navapp's dense algebra (numpy's and SciPy's BLAS) is loaded by then.
"""

from threadpoolctl import ThreadpoolController

_controller: ThreadpoolController | None = None


def limit_threads(limits: int = 1):
    """A context manager holding the BLAS / OpenMP pools at ``limits`` threads."""
    global _controller
    if _controller is None:
        _controller = ThreadpoolController()
    return _controller.limit(limits=limits)
