"""Numba's build of navapp's kernels split among threads (``threads.split_kernels``): the
home of ``split_jit`` and the chunk a task takes, for the compiled modules of ``geometry``
and ``registration``. Imports Numba: only the ``*_compiled`` modules and ``geometry.bvh``
import it. ``split_jit`` is None and ``prange`` is ``range`` where Numba is missing."""

try:
    from numba import njit, prange
except ImportError:  # pragma: no cover - only without numba
    njit, prange = None, range

# points (or rows) a task: small enough that a thread the machine does not run holds back
# little, large enough that a task is not all overhead (docs/decisions/speed.md, "The live
# update on two cores")
CHUNK = 16


def split_jit(fn, **options):
    """``fn`` compiled with its ``prange`` loops over chunks split among Numba's threads (TBB's,
    each chunk taken by whichever thread is free); its own function, so Numba's disk cache
    keeps it apart from the one-thread build. None where Numba is missing."""
    return njit(cache=True, nogil=True, parallel=True, **options)(fn) if njit is not None else None
