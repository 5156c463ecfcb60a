"""Where a study's tasks run (local processes, or a Dask distributed cluster with
``--scheduler ADDRESS``) and where their rows go (a results CSV created with its first rows,
so that a run that fails before any result leaves no empty file behind).

A scheduler address is checked before any work (``check_scheduler``): an unreachable one
was found only after the local cache warm-up, 42 s in, and after the CSV was created.
"""

import csv
import os
import threading
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from ..errors import NavappError

DASK_CONNECT_S = 10  # how long to wait for a scheduler before saying it does not answer
DASK_HANDSHAKE_S = 10  # beyond that, for a listener to prove it is one


def dask_client(address, client_class=None):
    """A Dask ``Client`` on ``address``; an address where no scheduler answers (or a
    malformed one) raises ``NavappError`` in one line instead of distributed's traceback."""
    if client_class is None:
        try:
            from distributed import Client
        except ImportError:
            raise NavappError("--scheduler needs Dask distributed: pip install -e '.[study]'") from None
        client_class = Client
    # distributed's own timeout covers the TCP connect, not the handshake after it: a port that
    # accepts and stays silent held the study for minutes, and one that answers with something
    # else made distributed read a length out of the reply and fail allocating it (reported as
    # "out of memory"). So the whole connect runs under one bound of ours, and anything it
    # raises means "not a Dask scheduler".
    box: dict = {}

    def connect():
        try:
            box["client"] = client_class(address, timeout=f"{DASK_CONNECT_S}s")
        except BaseException as exc:  # noqa: BLE001 — carried to the caller's thread and said in one line
            box["error"] = exc

    t = threading.Thread(target=connect, name="navapp-dask-connect", daemon=True)
    t.start()
    t.join(DASK_CONNECT_S + DASK_HANDSHAKE_S)
    if "client" in box:
        return box["client"]
    exc = box.get("error")
    if exc is None:
        raise NavappError(f"--scheduler {address}: something accepts connections there but no Dask scheduler "
                          f"answered within {DASK_CONNECT_S + DASK_HANDSHAKE_S} s; check the address or drop "
                          f"--scheduler")
    if isinstance(exc, (OSError, TimeoutError, ValueError)):
        raise NavappError(f"--scheduler {address}: no Dask scheduler answers there within {DASK_CONNECT_S} s "
                          f"({exc.__class__.__name__}); start one with `dask scheduler` or drop --scheduler") from None
    raise NavappError(f"--scheduler {address}: what answers there is not a Dask scheduler "
                      f"({exc.__class__.__name__}); check the address or drop --scheduler") from None


def check_scheduler(address):
    """Connect to ``address`` and let go: raises ``NavappError`` in one line if no
    scheduler answers, before the study does any work."""
    with dask_client(address):
        pass


def run_tasks(fn, tasks, scheduler=None, workers=1):
    """Results of ``fn(*args)`` for each ``args`` in ``tasks``, yielded as they complete:
    on the Dask scheduler at ``scheduler``, else on ``workers`` local processes (in this
    process when ``workers`` is 1: a study that measures time then runs undisturbed)."""
    tasks = list(tasks)
    if scheduler:
        try:
            from distributed import as_completed as dask_completed
        except ImportError:
            raise NavappError("--scheduler needs Dask distributed: pip install -e '.[study]'") from None
        with dask_client(scheduler) as client:
            futures = [client.submit(fn, *args, pure=False) for args in tasks]
            for fut in dask_completed(futures):
                yield fut.result()
        return
    if workers == 1 or len(tasks) <= 1:
        for args in tasks:
            yield fn(*args)
        return
    with ProcessPoolExecutor(max_workers=workers or os.cpu_count()) as pool:
        for fut in as_completed([pool.submit(fn, *args) for args in tasks]):
            yield fut.result()


class ResultsCSV:
    """Rows appended to a CSV as they arrive, flushed each time; the file (with its
    header, when new) is created with the first rows, never empty."""

    def __init__(self, path, columns):
        self.path, self.columns, self._file, self._writer = Path(path), tuple(columns), None, None

    def write(self, rows):
        rows = list(rows)
        if not rows:
            return
        if self._file is None or self._writer is None:
            new = not self.path.exists() or self.path.stat().st_size == 0
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = self.path.open("a", newline="")
            self._writer = csv.DictWriter(self._file, self.columns)
            if new:
                self._writer.writeheader()
        self._writer.writerows(rows)
        self._file.flush()

    def close(self):
        if self._file is not None:
            self._file.close()
            self._file, self._writer = None, None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
