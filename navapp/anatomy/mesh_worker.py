"""Child process of ``meshing.tetrahedralise``:
``python -m navapp.anatomy.mesh_worker IN OUT PARENT [WATCH_FD]``.

Reads the surface and the attempt from IN (.npz), meshes, and writes ``nodes`` and
``tets`` (or ``error``, one line) to OUT. Runs apart so that the parent can stop a mesher
that overruns its work budget; dies with its parent. WATCH_FD is the read end of a pipe
whose write end only the parent holds: a small process forked from here waits on it and
removes IN's temporary folder once the parent is gone, whether it finished or was killed
(a caller killed by SIGKILL can remove nothing, and its folder stayed until the next run).
"""

import os
import shutil
import signal
import sys
import time
from pathlib import Path

from ..errors import NavappError

# only a meshing attempt's own temporary folder is ever removed (``meshing.TEMP_PREFIX``, not
# imported: meshing imports this module's caller side, and loads numpy and trimesh)
FOLDER_PREFIX = "navapp-mesh-"


def _die_with_parent(parent: int):
    """On Linux, ask the kernel to kill this process when its parent dies (fTetWild holds
    the GIL, so no Python thread could act while it works). Done before numpy, Gmsh or
    navapp's meshing module are imported: that import takes seconds on a busy machine, and
    a mesher killed with its caller must not live on through it."""
    try:
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(3)


def _exit_with_parent(parent: int):
    """Where PR_SET_PDEATHSIG does not exist: end the process once its parent is gone
    (Gmsh runs in C with the GIL released, so this thread runs while it works)."""

    while True:
        time.sleep(1.0)
        if os.getppid() != parent:
            os._exit(3)


def _clean_up_after_parent(watch_fd: int, folder: Path):
    """Fork a process that removes ``folder`` when ``watch_fd`` reads end of file, i.e. when
    the parent has closed the pipe's write end: after the attempt (the folder is gone then),
    or by dying. Forked before numpy or a mesher is loaded (a small copy), with no death
    signal of its own (it must outlive this mesher, which dies with the parent) and deaf to
    the terminal's Ctrl+C and hang-up and to a group's SIGTERM: it ends on the pipe alone."""
    if not hasattr(os, "fork") or not folder.name.startswith(FOLDER_PREFIX):
        return
    if os.fork() == 0:
        try:
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
                signal.signal(sig, signal.SIG_IGN)
            os.chdir("/")
            while os.read(watch_fd, 64):
                pass
            shutil.rmtree(folder, ignore_errors=True)
        finally:
            os._exit(0)
    os.close(watch_fd)


def main(src: str, dst: str, parent: int | None = None, watch_fd: int | None = None) -> int:
    if watch_fd is not None:
        _clean_up_after_parent(watch_fd, Path(src).resolve().parent)
    if parent is not None:
        _die_with_parent(parent)
        import threading

        threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()
    import numpy as np

    from .mesh_engines import ftetwild_mesh, gmsh_mesh

    with np.load(src) as a:
        v, f, edge, seed = a["vertices"], a["faces"], float(a["edge"]), int(a["seed"])
        method, angle = str(a["method"]), float(a["feature_angle"])
        volume = str(a["volume"]) if "volume" in a else "delaunay"
    try:
        if method == "gmsh":
            nodes, tets = gmsh_mesh(v, f, edge, seed, angle, volume)
        elif method == "ftetwild":
            nodes, tets = ftetwild_mesh(v, f, edge)
        else:
            raise NavappError(f"unknown meshing method {method!r}")
        if len(tets) == 0:
            raise NavappError(f"{method} produced no tetrahedra")
    except NavappError as exc:
        np.savez(dst, error=str(exc))
        return 0
    np.savez(dst, nodes=nodes, tets=tets)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else None,
                  int(sys.argv[4]) if len(sys.argv) > 4 else None))
