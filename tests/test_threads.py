"""navapp.threads.limit_threads: the BLAS / OpenMP pools are held at one thread inside and
given back after, like threadpoolctl.threadpool_limits (which it replaces for its cost)."""

import numpy as np
from threadpoolctl import threadpool_info

from navapp.threads import limit_threads


def pools():
    return {(p["internal_api"], p["filepath"]): p["num_threads"] for p in threadpool_info()}


def test_limit_threads_holds_one_thread_inside_and_restores_after():
    np.ones((4, 4)) @ np.ones((4, 4))  # BLAS loaded
    before = pools()
    with limit_threads(1):
        inside = pools()
        with limit_threads(1):  # nested, as the LM loop inside a live update
            pass
        assert pools() == inside
    assert all(n == 1 for n in inside.values()), inside
    assert pools() == before
