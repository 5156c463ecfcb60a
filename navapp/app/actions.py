"""The session's action log: every change a tab made to the shared data, with its time, tab
and role, one JSON object a line in ``actions.jsonl`` in the session folder. No viser here.

Append-only: a line is written, flushed and fsync'd before the change is acknowledged, so a
kill -9 loses at most the line being written, and that line is cut off at the next start
(a partial line was never acknowledged). Nothing rewrites or removes a line; the session's
first save carries the file into its folder and Export copies it.
"""

from __future__ import annotations

import json
import os
import threading
import time
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

from .access import Role

FILE = "actions.jsonl"


class Act(Enum):
    """What a line records (its value is the log's words)."""

    POINTS = "points digitised"
    SWEEP = "stylus sweep"
    PLANE = "plane added"
    FREE_PLANE = "free plane placed"
    VERTEX = "contour vertex"
    COMMIT = "contour committed"
    CLEAR = "plane cleared"
    UNDO = "undone"
    REMOVE = "point removed"
    RUN = "run started"
    CANCEL = "run cancelled"
    FINISHED = "run finished"
    CHOSEN = "run chosen"
    ACCURACY = "accuracy sweep started"
    EXPORT = "exported"
    SLICER = "sent to 3D Slicer"
    FROZEN = "frame frozen"
    RECORDING = "live recording"
    FOLLOW = "live re-registration"
    POSE = "pose of the data stated"
    SUPPORTS = "supports stated"


@dataclass(frozen=True)
class Entry:
    time: str  # UTC, ISO 8601 to the millisecond
    tab: str  # "tab 3" (the viewer's connection number), or "server" for what follows a tab's action
    role: str  # Role.value, or "server"
    act: Act
    detail: str = ""

    def to_json(self) -> dict:
        return {"time": self.time, "tab": self.tab, "role": self.role, "action": self.act.value,
                "detail": self.detail}

    @staticmethod
    def from_json(d: dict) -> Entry:
        return Entry(str(d["time"]), str(d["tab"]), str(d["role"]), Act(d["action"]), str(d.get("detail", "")))

    def line(self) -> str:
        """The entry in the viewer's log panel."""
        who = self.tab if self.role in ("editor", "server") else f"{self.tab} ({self.role})"
        return f"{self.time[11:19]} {who}: {self.act.value}" + (f" — {self.detail}" if self.detail else "")


def now_utc() -> str:
    t = time.time()
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + f".{int(t % 1 * 1000):03d}Z"


class ActionLog:
    """``folder``'s action log. ``folder`` is read at each append (the session's first save
    renames a new folder into place: the path stays, the directory behind it changes)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self._lock = threading.Lock()
        self._entries: list[Entry] = []
        self.unreadable = 0  # lines damaged outside navapp: kept in the file, not shown
        self._read()

    @property
    def path(self) -> Path:
        return self.folder / FILE

    def _read(self):
        path = self.path
        if not path.is_file():
            return
        raw = path.read_bytes()
        whole = raw[: raw.rfind(b"\n") + 1]  # a line cut by a kill mid-write was never acknowledged
        if len(whole) != len(raw):
            with open(path, "r+b") as f:
                f.truncate(len(whole))
                os.fsync(f.fileno())
        for line in whole.decode("utf-8", errors="replace").splitlines():
            if not line.strip():
                continue
            try:
                self._entries.append(Entry.from_json(json.loads(line)))
            except (ValueError, KeyError, TypeError):
                self.unreadable += 1

    def append(self, tab: str, role: Role | str, act: Act, detail: str = "") -> Entry:
        entry = Entry(now_utc(), tab, role.value if isinstance(role, Role) else role, act, detail)
        data = (json.dumps(entry.to_json(), ensure_ascii=False) + "\n").encode()
        with self._lock:
            self.folder.mkdir(parents=True, exist_ok=True)
            new = not self.path.exists()
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            try:
                os.write(fd, data)
                os.fsync(fd)
            finally:
                os.close(fd)
            if new:  # the file's name must survive a crash too
                dfd = os.open(self.folder, os.O_RDONLY)
                try:
                    os.fsync(dfd)
                finally:
                    os.close(dfd)
            self._entries.append(entry)
        return entry

    def entries(self) -> list[Entry]:
        with self._lock:
            return list(self._entries)


def interrupted_run(entries: list[Entry]) -> Entry | None:
    """The last run started with no end after it (the server was killed while it ran), or None."""
    for e in reversed(entries):
        if e.act is Act.FINISHED:
            return None
        if e.act is Act.RUN:
            return e
    return None
