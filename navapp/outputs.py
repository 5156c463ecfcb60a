"""Output folders: one run writes a folder at a time, and a folder appears whole or not at all.

``folder_lock(out)`` holds an exclusive ``flock`` on a lock file named by the folder's path
for the whole run: a second run on the same folder stops at once with one line naming the
first (pid, command, start time). The kernel drops the lock when its process ends, even by
``kill -9``, so a lock is never stale. Held locks are counted per process, so code under
a lock may take it again.

``staged(out)`` yields a temporary folder beside ``out``; when the block ends without an
error the old folder is renamed away, the new one renamed into place, and the old one
deleted. A run killed while writing leaves ``out`` as it was (its leftovers are removed
by the next run on that folder).

``replaced(path)`` is the same for one file: written beside it under a temporary name, renamed
over it when complete (the cache's arrays, the viewer's session files).

``write_registered`` writes the registered model's surfaces: the one writer of ``navapp
register``'s output folder and the viewer's Export.
"""

import fcntl
import os
import shutil
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

from .errors import NavappError

_held: dict[Path, list] = {}  # lock path → [open file, depth], this process's locks


LOCK_DIR = Path(tempfile.gettempdir()) / "navapp-locks"


def lock_path(out) -> Path:
    """The lock file of output folder ``out``: named by its resolved path, kept in the
    temporary folder so that locking creates nothing in the user's folders (a mistyped
    case path must still read as missing)."""
    import hashlib

    key = hashlib.sha256(str(Path(out).resolve()).encode()).hexdigest()[:32]
    return LOCK_DIR / f"{key}.lock"


@contextmanager
def folder_lock(out, kind: str = "folder"):
    """Hold the lock on output folder ``out`` (or any path a run writes: a study's results
    file, ``kind`` naming it in the message) for the block; raise ``NavappError`` in one line
    when another process holds it."""
    path = lock_path(out)
    if path in _held:
        _held[path][1] += 1
        try:
            yield
        finally:
            _held[path][1] -= 1
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    f = open(path, "a+")
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.seek(0)
        holder = f.read().strip() or "another process"
        f.close()
        where = "(--out)" if kind == "folder" else "(--results, --report)"
        raise NavappError(f"{Path(out)}: another navapp run is writing this {kind} ({holder}); wait for it to "
                          f"finish or write elsewhere {where}") from None
    f.seek(0)
    f.truncate()
    command = " ".join(["navapp", *sys.argv[1:]]) if sys.argv and sys.argv[0] else "navapp"
    f.write(f"pid {os.getpid()}, `{command[:120]}`, since {time.strftime('%H:%M:%S')}")
    f.flush()
    _held[path] = [f, 1]
    try:
        yield
    finally:
        del _held[path]
        f.seek(0)
        f.truncate()
        fcntl.flock(f, fcntl.LOCK_UN)
        f.close()


def write_registered(folder, transform, surfaces: dict, prefix: str = "", vtk: bool = False) -> list[Path]:
    """The registered model's surfaces into ``folder``: each preoperative surface of
    ``surfaces`` (name → trimesh.Trimesh, or None: skipped) with its vertices (V, 3) mm mapped
    by ``transform`` ((P, 3) → (P, 3) mm, preoperative → tracker space), as binary PLY
    ``{prefix}{name}.ply`` and, with ``vtk``, legacy ASCII VTK ``{prefix}{name}.vtk`` (3D
    Slicer reads it). Returns the files written."""
    import meshio
    import numpy as np
    import trimesh

    folder = Path(folder)
    written = []
    for name, mesh in surfaces.items():
        if mesh is None:
            continue
        v = np.asarray(transform(mesh.vertices), float)
        ply = folder / f"{prefix}{name}.ply"
        trimesh.Trimesh(v, mesh.faces, process=False).export(ply, encoding="binary")
        written.append(ply)
        if vtk:
            meshio.write(folder / f"{prefix}{name}.vtk", meshio.Mesh(v, [("triangle", np.asarray(mesh.faces))]),
                         binary=False)
            written.append(folder / f"{prefix}{name}.vtk")
    return written


def _leftovers(out: Path):
    return [p for p in out.parent.glob(f".{out.name}.*-*") if p.is_dir()]


@contextmanager
def staged(out):
    """Yield a temporary folder to write ``out``'s new content into; on success it
    replaces ``out`` whole. Call under ``folder_lock(out)``."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for old in _leftovers(out):  # a run killed while writing: its half-written folder
        shutil.rmtree(old, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.new-", dir=out.parent))
    umask = os.umask(0)
    os.umask(umask)
    tmp.chmod(0o777 & ~umask)  # mkdtemp's 0700 would become the output folder's mode
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    try:
        replace_folder(tmp, out, old / "content")
    finally:
        shutil.rmtree(old, ignore_errors=True)


@contextmanager
def replaced(path, tmp: str | None = None):
    """Yield a temporary path beside ``path`` to write the file into; when the block ends
    without an error it replaces ``path`` by one rename (atomic on one file system: a reader
    sees the old file or the new one, never half of it), after an error it is removed and
    ``path`` is as it was. ``tmp``: its name in ``path``'s folder (a caller that cleans up
    after a kill by name), else a fresh unique one (several processes may write ``path``).
    The one way navapp writes a file that must never be seen half written."""
    path = Path(path)
    if tmp is None:
        fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.close(fd)
        new = Path(name)
    else:
        new = path.parent / tmp
    try:
        yield new
        os.replace(new, path)
    except BaseException:
        new.unlink(missing_ok=True)
        raise


def replace_folder(new: Path, folder: Path, aside: Path) -> None:
    """Put the finished folder ``new`` where ``folder`` is, whole: the one way navapp swaps a
    folder in (``staged``, the viewer's first session save). ``new`` and ``aside`` lie beside
    ``folder`` (the same file system: renames are atomic); ``aside`` does not exist. An absent
    or empty ``folder`` is replaced by one rename (rename(2) replaces an empty folder);
    otherwise the old one is renamed to ``aside``, ``new`` renamed in, and ``aside`` deleted,
    so that a kill at any point leaves ``folder`` either old or new, never half of each (the
    caller names ``new`` and ``aside`` so that its next start removes what a kill left)."""
    if not folder.exists() or not any(folder.iterdir()):
        os.replace(new, folder)
        return
    os.replace(folder, aside)
    os.replace(new, folder)
    shutil.rmtree(aside, ignore_errors=True)
