"""Progress shown on anything slow: tqdm bars on stderr, and a ticking stage timer for
calls that report no progress of their own (e.g. Gmsh)."""

import sys
import threading
import time
from contextlib import contextmanager

from tqdm import tqdm

QUIET = False  # set by the CLI's --quiet and by tests


def bar(total, desc, unit="it"):
    """A tqdm bar on stderr (hidden when QUIET)."""
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, disable=QUIET, leave=False,
                dynamic_ncols=True, mininterval=0.2)


@contextmanager
def stage(desc):
    """Show ``desc`` with elapsed seconds ticking while the block runs; yields a dict that
    receives ``seconds`` when the block ends."""
    out = {}
    stop = threading.Event()
    t0 = time.perf_counter()

    def tick():
        with tqdm(desc=desc, bar_format="{desc}: {elapsed}", file=sys.stderr, disable=QUIET, leave=False) as t:
            while not stop.wait(0.5):
                t.refresh()

    th = threading.Thread(target=tick, daemon=True)
    th.start()
    try:
        yield out
    finally:
        stop.set()
        th.join()
        out["seconds"] = time.perf_counter() - t0
