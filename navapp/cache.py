"""Content-addressed cache of numpy arrays, written atomically and verified on load.

A cache entry is one ``.npz`` file named by a SHA-256 of everything its content depends
on. It holds the arrays plus a digest of their bytes; a file that is truncated, corrupt or
whose digest does not match is reported in one line and treated as absent, never loaded.
"""

import hashlib
import json
import os
import sys
import zipfile
from pathlib import Path

import numpy as np

from .outputs import replaced

CACHE_VERSION = "1"


def cache_dir() -> Path:
    """``$NAVAPP_CACHE`` or ``~/.cache/navapp``."""
    return Path(os.environ.get("NAVAPP_CACHE", Path.home() / ".cache" / "navapp"))


def content_key(*parts) -> str:
    """SHA-256 hex of the parts: arrays by dtype, shape and bytes; everything else by JSON."""
    h = hashlib.sha256(CACHE_VERSION.encode())
    for p in parts:
        if isinstance(p, np.ndarray):
            a = np.ascontiguousarray(p)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
        else:
            h.update(json.dumps(p, sort_keys=True, default=str).encode())
        h.update(b"|")
    return h.hexdigest()


def _digest(arrays: dict) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode())
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save(path: Path, arrays: dict):
    """Write arrays to ``path`` atomically (temporary file in the same folder, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = dict(arrays)
    payload["__digest__"] = np.array(_digest(arrays))
    with replaced(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **payload)


def load(path: Path, report=True) -> dict | None:
    """The arrays stored at ``path``, or None if absent or damaged (damage is reported)."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        digest = str(arrays.pop("__digest__"))
        if digest != _digest(arrays):
            raise ValueError("content digest mismatch")
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as exc:
        if report:
            print(f"navapp: cache file {path} is damaged ({exc}); recomputing", file=sys.stderr)
        path.unlink(missing_ok=True)
        return None
    return arrays
