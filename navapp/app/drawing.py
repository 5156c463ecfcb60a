"""Drawing on an ultrasound image, and undo: a click adds a vertex to the contour this tab is
drawing, Close / Finish line / Clear plane end or remove contours, and every change a tab
makes to the shared data is a ``state.Action`` that knows how to undo itself. Undo is per tab:
it walks back that tab's own actions, skipping those whose work is gone meanwhile, and
never touches another tab's. No viser here.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from .contours import Contour
from .core import Core
from .palette import DRAWABLE
from .session import Session
from .state import Action, Change, ClientState, Undone


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

    def click(self, cs: ClientState, col: int, row: int, feature: str | None = None) -> str | None:
        """A vertex at image pixel (col, row) of this browser's plane; returns an error or None."""
        core = self.core
        sd, session = core.need_scene()
        if cs.plane is None:
            return "Choose a plane first."
        if not (0 <= col < sd.probe.width_px and 0 <= row < sd.probe.height_px):
            return "That click is outside the image."
        name = feature if feature in DRAWABLE else cs.feature
        with core.lock:
            cs.feature = name
            c = cs.drawing
            if c is None or c.plane != cs.plane or c.feature != DRAWABLE[name] or c.closed \
                    or c not in session.contours:
                c = cs.drawing = Contour(cs.plane, DRAWABLE[name])
                session.contours.append(c)
            c.vertices.append((int(col), int(row)))
            cs.undo.append(VertexAdded(session, c))
            cs.touch()
        core.changed(Change.DATA)
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
            elif command is Command.FINISH:
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
            cs.message = msg or ""
            cs.touch()
        core.changed(Change.DATA)
        return msg

    def undo(self, cs: ClientState) -> str | None:
        """Undo this browser's last action of any kind; others' work is left alone."""
        with self.core.lock:
            while cs.undo:
                a = cs.undo.pop()
                out = a.undo(cs)
                if out is Undone.DONE:
                    return None
                if isinstance(out, str):
                    cs.undo.append(a)  # kept: it can be undone once the reason is gone
                    return out
        return "Nothing of yours to undo."
