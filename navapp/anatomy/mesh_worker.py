"""Child process of ``meshing.tetrahedralise``: ``python -m navapp.anatomy.mesh_worker IN OUT PARENT``.

Reads the surface and the attempt from IN (.npz), meshes, and writes ``nodes`` and
``tets`` (or ``error``, one line) to OUT. Runs apart so that the parent can stop a mesher
that overruns its work budget; dies with its parent.
"""

import os
import sys
import time

from ..errors import NavappError


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


def main(src: str, dst: str, parent: int | None = None) -> int:
    if parent is not None:
        _die_with_parent(parent)
        import threading

        threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()
    import numpy as np

    from .meshing import ftetwild_mesh, gmsh_mesh

    with np.load(src) as a:
        v, f, edge, seed = a["vertices"], a["faces"], float(a["edge"]), int(a["seed"])
        method, angle = str(a["method"]), float(a["feature_angle"])
    try:
        if method == "gmsh":
            nodes, tets = gmsh_mesh(v, f, edge, seed, angle)
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
    sys.exit(main(sys.argv[1], sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else None))
