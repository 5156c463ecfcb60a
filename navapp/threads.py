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

from threadpoolctl import ThreadpoolController

_controller: ThreadpoolController | None = None
_modules = -1  # len(sys.modules) when it was made


def limit_threads(limits: int = 1):
    """A context manager holding the BLAS / OpenMP pools at ``limits`` threads."""
    global _controller, _modules
    if _controller is None or len(sys.modules) != _modules:
        _controller, _modules = ThreadpoolController(), len(sys.modules)
    return _controller.limit(limits=limits)
