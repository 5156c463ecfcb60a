"""Drawing on an ultrasound image, and undo: a click adds a vertex to the contour this tab is
drawing, Close / Finish line / Clear plane end or remove contours, and every change a tab
makes to the shared data is a ``state.Action`` that knows how to undo itself. Undo is per tab:
it walks back that tab's own actions, skipping those whose work is gone meanwhile, and
never touches another tab's. No viser here.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from enum import Enum

import numpy as np

from .access import Role
from .actions import Act
from .contours import Contour
from .core import Core
from .palette import DRAWABLE
from .session import Session
from .state import Action, Change, ClientState, Undone, WorstPoint


@dataclass
class VertexAdded(Action):
    session: Session
    contour: Contour

    def undo(self, cs):
        c, session = self.contour, self.session
        if c not in session.contours or not c.vertices:
            return Undone.GONE
        c.vertices.pop()
        c.closed = False
        if not c.vertices:
            session.contours.remove(c)
            cs.drawing = None
        else:
            cs.drawing, cs.plane = c, c.plane
        return Undone.DONE


@dataclass
class Closed(Action):
    session: Session
    contour: Contour

    def undo(self, cs):
        if self.contour not in self.session.contours:
            return Undone.GONE
        self.contour.closed = False
        cs.drawing, cs.plane = self.contour, self.contour.plane
        return Undone.DONE


@dataclass
class Cleared(Action):
    session: Session
    plane: int
    removed: list[Contour]
    was_added: bool  # the plane's segmentation was data

    def undo(self, cs):
        session = self.session
        session.contours.extend(self.removed)
        if self.was_added and self.plane not in session.planes_added:
            session.planes_added.append(self.plane)
        return Undone.DONE


@dataclass
class VertexRemoved(Action):
    """A drawn vertex removed from the worst-points list (a wrong click)."""

    session: Session
    contour: Contour
    index: int
    vertex: tuple[int, int]
    was_closed: bool
    dropped: bool  # the contour had no vertex left and left the session

    def undo(self, cs):
        c, session = self.contour, self.session
        if self.dropped:
            session.contours.append(c)
        elif c not in session.contours:
            return Undone.GONE
        c.vertices.insert(min(self.index, len(c.vertices)), self.vertex)
        c.closed = self.was_closed
        return Undone.DONE


@dataclass
class PointExcluded(Action):
    """A data point (stylus, segmentation, contour centre) removed from the worst-points list."""

    session: Session
    entry: list

    def undo(self, cs):
        if self.entry not in self.session.excluded:
            return Undone.GONE
        self.session.excluded.remove(self.entry)
        return Undone.DONE


class Command(Enum):
    """The 2D view's and the Ultrasound panel's contour commands (the value is the button's words)."""

    CLOSE = "Close"
    FINISH = "Finish line"
    UNDO = "Undo"
    CLEAR = "Clear plane"
    FEATURE = "Feature"


class Drawing:
    def __init__(self, core: Core):
        self.core = core
        core.tab_state = self.tabs_json

    # ------------------------------------------------------------------ a tab's work across a restart
    def tabs_json(self) -> dict:
        """Each editing tab's own work (under ``Core.lock``): its plane, drawing tool, guide step,
        the contour it is drawing and those it left unfinished on other planes (indices into the
        session's contours) and its undo history of vertices and closes (``session.write_tabs``).
        Other undoable actions (planes added, removals, recordings) are not carried over a restart."""
        core = self.core
        session = core.session
        if session is None:
            return {}

        def index(c: Contour | None) -> int | None:
            return next((i for i, x in enumerate(session.contours) if x is c), None)

        out = {}
        for cs in [*core.parked.values(), *core.states.values()]:
            if cs.role is not Role.EDITOR or cs.successor is not None:
                continue
            undo = [[TAB_UNDO[type(a)], i] for a in cs.undo
                    if isinstance(a, (VertexAdded, Closed)) and (i := index(a.contour)) is not None]
            out[cs.token] = {"plane": cs.plane, "feature": cs.feature, "guide_step": cs.guide_step,
                             "drawing": index(cs.drawing),
                             "left": {str(p): index(c) for p, c in cs.left.items() if index(c) is not None},
                             "undo": undo}
        return out

    def restore_tabs(self, tabs: dict) -> int:
        """The tabs of ``tabs_json`` as parked tabs, each for its page to take back as a reload
        (``Core.resume``): after a restart the tab goes on with its plane, its unfinished contour
        and its undo history. Returns how many."""
        core = self.core
        session = core.need_session()
        n = len(session.contours)

        def contour(i) -> Contour | None:
            return session.contours[i] if isinstance(i, int) and 0 <= i < n else None

        now = time.monotonic()
        with core.lock:
            for token, d in tabs.items():
                try:
                    cs = ClientState(-1, str(token))
                    cs.plane = d["plane"] if isinstance(d.get("plane"), int) and d["plane"] in core.planes else None
                    cs.feature = d["feature"] if d.get("feature") in DRAWABLE else cs.feature
                    cs.guide_step = int(d.get("guide_step", 0))
                    cs.drawing = contour(d.get("drawing"))
                    cs.left = {int(p): c for p, i in dict(d.get("left", {})).items()
                               if (c := contour(i)) is not None}
                    for kind, i in d.get("undo", []):
                        c = contour(i)
                        if c is not None and kind in TAB_ACTION:
                            cs.undo.append(TAB_ACTION[kind](session, c))
                except (TypeError, ValueError, KeyError, AttributeError):
                    continue  # a damaged entry: that tab starts afresh
                cs.parked = now
                core.parked[cs.token] = cs
        return len(tabs)

    def click(self, cs: ClientState, col: int, row: int, feature: str | None = None,
              plane: int | None = None) -> str | None:
        """A vertex at image pixel (col, row) of ``plane``, the plane the click was aimed at
        (None: this browser's plane now); returns an error or None. A click queued in the
        page while the plane was changed elsewhere (the 3D panel, the guide, a suggestion)
        still lands where it was aimed, continuing the contour left unfinished there."""
        core = self.core
        sd, session = core.need_scene()
        target = cs.plane if plane is None else plane
        if target is None:
            return "Choose a plane first."
        if target not in core.planes:
            return "That click was aimed at a plane that is gone."
        if not (0 <= col < sd.probe.width_px and 0 <= row < sd.probe.height_px):
            return "That click is outside the image."
        name = feature if feature in DRAWABLE else cs.feature
        kind = DRAWABLE[name]

        def open_here(c: Contour | None) -> bool:
            return c is not None and c.plane == target and c.feature == kind and not c.closed \
                and c in session.contours

        with core.lock:
            here = target == cs.plane
            if here:
                cs.feature = name
                back = cs.left.pop(target, None)  # back on this plane: the contour left here goes on
                if cs.drawing is None and open_here(back):
                    cs.drawing = back
            c = cs.drawing if here else cs.left.get(target)
            if not open_here(c):
                c = Contour(target, kind)
                session.contours.append(c)
            assert c is not None
            if here:
                cs.drawing = c
            else:
                cs.left[target] = c
            c.vertices.append((int(col), int(row)))
            cs.undo.append(VertexAdded(session, c))
            cs.touch()
        core.changed(Change.DATA)
        core.record(cs, Act.VERTEX, f"{name} on plane {target}, pixel ({int(col)}, {int(row)}), "
                                    f"vertex {len(c.vertices)}")
        return None

    def command(self, cs: ClientState, cmd: str, feature: str | None = None) -> str | None:
        """Close / Finish line / Undo / Clear plane / Feature (``Command``'s words), for this
        browser; an error or None."""
        try:
            command = Command(cmd)
        except ValueError:
            return f"unknown command {cmd!r}"
        core = self.core
        session = core.need_session()
        msg = None
        done: tuple[Act, str] | None = None  # what the action log gets
        with core.lock:
            c = cs.drawing
            if command is Command.FEATURE:
                if feature in DRAWABLE:
                    cs.feature = feature
                    if c is not None and c.feature != DRAWABLE[feature]:
                        cs.drawing = None
                cs.touch()
                return None
            if command is Command.CLOSE:
                if c is None:
                    msg = "Nothing is being drawn."
                elif len(c.vertices) < 3:
                    msg = "A closed contour needs at least 3 vertices."
                else:
                    c.closed = True
                    cs.drawing = None
                    cs.undo.append(Closed(session, c))
                    done = Act.COMMIT, f"closed {c.feature} on plane {c.plane}, {len(c.vertices)} vertices"
            elif command is Command.FINISH:
                if c is not None and c.vertices:
                    done = Act.COMMIT, f"line {c.feature} on plane {c.plane}, {len(c.vertices)} vertices"
                cs.drawing = None
            elif command is Command.UNDO:
                msg = self.undo(cs)
            elif command is Command.CLEAR and cs.plane is not None:
                plane = cs.plane
                removed = [x for x in session.contours if x.plane == plane]
                session.contours = [x for x in session.contours if x.plane != plane]
                was_added = plane in session.planes_added
                if was_added:
                    session.planes_added.remove(plane)
                cs.undo.append(Cleared(session, plane, removed, was_added))
                cs.drawing = None
                done = Act.CLEAR, f"plane {plane}: {len(removed)} contours" + (
                    ", its segmentation" if was_added else "")
            cs.message = msg or ""
            cs.touch()
        core.changed(Change.DATA)
        if done is not None:
            core.record(cs, *done)
        return msg

    def gone(self, wp: WorstPoint) -> bool:
        """Whether a listed worst point is out of the data now (removed from the list, its
        contour cleared or undone): the list keeps it in its place, marked, until the next fit."""
        session = self.core.need_session()
        with self.core.lock:
            c = wp.origin.contour
            if c is not None and wp.vertex is not None:
                return c not in session.contours or wp.origin.vertex() is None
            return [*wp.point, wp.feature] in session.excluded

    def remove(self, cs: ClientState, wp: WorstPoint) -> str:
        """Remove one of the worst points (``Core.worst``) from the data, as this tab's undoable
        action: a drawn contour's point as the vertex it came from, any other point itself.
        Returns what happened, in words.

        The list is not renumbered: a point removed stays in its place, marked, so a second
        click on its button (a double click, or two tabs at once) finds it removed rather than
        taking the point listed after it. A drawn vertex is found by its pixel: an index taken
        when the list was made named the next vertex once an earlier one of its contour was
        removed."""
        core = self.core
        session = core.need_session()
        with core.lock:
            if self.gone(wp):
                return "That point is out of the data already."
            c, v = wp.origin.contour, wp.origin.vertex()
            if c is not None and v is not None and wp.vertex is not None:
                vertex = c.vertices.pop(v)
                was_closed = c.closed
                c.closed = c.closed and len(c.vertices) >= 3
                dropped = not c.vertices
                if dropped:
                    session.contours.remove(c)
                    if cs.drawing is c:
                        cs.drawing = None
                cs.undo.append(VertexRemoved(session, c, v, vertex, was_closed, dropped))
                msg = f"Removed the drawn vertex at pixel {vertex}."
            else:
                entry = [*wp.point, wp.feature]
                session.excluded.append(entry)
                cs.undo.append(PointExcluded(session, entry))
                msg = "Removed the point."
            cs.touch()
        core.changed(Change.DATA)
        core.record(cs, Act.REMOVE, f"{wp.feature} at {np.round(wp.point, 1).tolist()} mm: {msg}")
        return f"{msg} Register again to see the fit without it (Undo brings it back)."

    def undo(self, cs: ClientState) -> str | None:
        """Undo this browser's last action of any kind; others' work is left alone."""
        with self.core.lock:
            while cs.undo:
                a = cs.undo.pop()
                out = a.undo(cs)
                if out is Undone.DONE:
                    self.core.record(cs, Act.UNDO, _words(type(a).__name__))
                    return None
                if isinstance(out, str):
                    cs.undo.append(a)  # kept: it can be undone once the reason is gone
                    return out
        return "Nothing of yours to undo."


def _words(name: str) -> str:
    """An action's class name in the log's words: ``VertexAdded`` -> "vertex added"."""
    return re.sub(r"(?<!^)([A-Z])", r" \1", name).lower()


TAB_UNDO = {VertexAdded: "vertex", Closed: "closed"}  # the undo actions a tab keeps over a restart
TAB_ACTION = {v: k for k, v in TAB_UNDO.items()}
