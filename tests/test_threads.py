"""navapp.threads.limit_threads: the BLAS / OpenMP pools are held at one thread inside and
given back after, like threadpoolctl.threadpool_limits (which it replaces for its cost)."""

import numpy as np
from threadpoolctl import threadpool_info

from navapp.threads import limit_threads


def pools():
    return {(p["internal_api"], p["filepath"]): p["num_threads"] for p in threadpool_info()}


def test_limit_threads_holds_one_thread_inside_and_restores_after():
    from threadpoolctl import threadpool_limits

    np.ones((4, 4)) @ np.ones((4, 4))  # BLAS loaded
    # pools of two threads to begin with: the suite's workers run theirs at one (conftest),
    # where holding them at one and giving them back would show nothing
    with threadpool_limits(2):
        before = pools()
        assert all(n == 2 for n in before.values()), before
        with limit_threads(1):
            inside = pools()
            with limit_threads(1):  # nested, as the LM loop inside a live update
                pass
            assert pools() == inside
        assert all(n == 1 for n in inside.values()), inside
        assert pools() == before


def test_a_thread_pool_loaded_after_the_first_limit_is_held_too():
    """The controller was made once: a library imported after the first limit (here
    scikit-learn's OpenMP and SciPy's second OpenBLAS) kept its threads inside the limit (the
    two-worker suite found it). In a fresh process, where nothing else has loaded them yet."""
    import json
    import subprocess
    import sys

    code = ("import json, numpy as np\n"
            "from navapp.threads import limit_threads\n"
            "with limit_threads(1): pass\n"
            "import sklearn.linear_model\n"
            "from threadpoolctl import threadpool_info\n"
            "with limit_threads(1):\n"
            "    print(json.dumps([p['num_threads'] for p in threadpool_info()]))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600,
                         env={**__import__("os").environ, "OMP_NUM_THREADS": "2", "OPENBLAS_NUM_THREADS": "2"})
    assert out.returncode == 0, out.stderr
    assert all(n == 1 for n in json.loads(out.stdout.strip().splitlines()[-1])), out.stdout


def test_a_nested_limit_of_another_count_still_applies_and_gives_back():
    """A limit inside one of the same count is free (the outer holds the pools); one of another
    count is applied and undone as before."""
    from threadpoolctl import threadpool_limits

    np.ones((4, 4)) @ np.ones((4, 4))
    with threadpool_limits(2):
        with limit_threads(1):
            inside = pools()
            with limit_threads(2):
                assert all(n == 2 for n in pools().values()), pools()
                with limit_threads(2):
                    assert all(n == 2 for n in pools().values())
            assert pools() == inside
            with limit_threads(1):
                assert pools() == inside
        assert all(n == 2 for n in pools().values())
