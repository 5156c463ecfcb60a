"""Drawing on an ultrasound image, and undo: a click adds a vertex to the contour this tab is
drawing, Close / Finish line / Clear plane end or remove contours, and every change a tab
makes to the shared data is an ``Action`` that knows how to undo itself. Undo is per tab:
it walks back that tab's own actions, skipping those whose work is gone meanwhile, and
never touches another tab's. No viser here.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING

from .contours import Contour
from .palette import DRAWABLE
from .state import Change, ClientState

if TYPE_CHECKING:
    from .server import App


class Undone(Enum):
    DONE = "done"
    GONE = "gone"  # nothing of the action is left (removed meanwhile): undo the one before


class Action:
    """One undoable change a tab made to the shared data. ``undo`` runs under the shared
    lock and returns DONE, GONE, or why it cannot be undone now (the action is kept)."""

    def undo(self, app: App, cs: ClientState) -> Undone | str:
        raise NotImplementedError


@dataclass
class VertexAdded(Action):
    contour: Contour

    def undo(self, app, cs):
        c, session = self.contour, app.core.need_session()
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
    contour: Contour

    def undo(self, app, cs):
        if self.contour not in app.core.need_session().contours:
            return Undone.GONE
        self.contour.closed = False
        cs.drawing, cs.plane = self.contour, self.contour.plane
        return Undone.DONE


@dataclass
class Cleared(Action):
    plane: int
    removed: list[Contour]
    was_added: bool  # the plane's segmentation was data

    def undo(self, app, cs):
        session = app.core.need_session()
        session.contours.extend(self.removed)
        if self.was_added and self.plane not in session.planes_added:
            session.planes_added.append(self.plane)
        return Undone.DONE


@dataclass
class PlaneAdded(Action):
    plane: int

    def undo(self, app, cs):
        session = app.core.need_session()
        if self.plane not in session.planes_added:
            return Undone.GONE
        session.planes_added.remove(self.plane)
        return Undone.DONE


@dataclass
class FreePlanePlaced(Action):
    plane: int

    def undo(self, app, cs):
        core = app.core
        session = core.need_session()
        if any(c.plane == self.plane for c in session.contours) or self.plane in session.planes_added:
            return "That free plane has contours or data on it now; clear it first."
        session.free_planes = [f for f in session.free_planes if f["index"] != self.plane]
        core.planes.pop(self.plane, None)
        if cs.plane == self.plane:
            cs.plane = None
        return Undone.DONE


@dataclass
class StylusBatch(Action):
    before: int  # points digitised before the sweep

    def undo(self, app, cs):
        if app.stylus.sweeping:
            return "Stop the stylus sweep first."
        session = app.core.need_session()
        session.stylus_count = min(session.stylus_count, self.before)
        return Undone.DONE


@dataclass
class LivePoints(Action):
    before: int  # live points before the recording

    def undo(self, app, cs):
        if app.live.recording:
            return "Stop digitising first."
        del app.core.need_session().live_points[self.before:]
        return Undone.DONE


class Command(Enum):
    """The 2D view's and the Ultrasound panel's contour commands (the value is the button's words)."""

    CLOSE = "Close"
    FINISH = "Finish line"
    UNDO = "Undo"
    CLEAR = "Clear plane"
    FEATURE = "Feature"


class Drawing:
    def __init__(self, app: App):
        self.app, self.core = app, app.core

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
            cs.undo.append(VertexAdded(c))
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
                    cs.undo.append(Closed(c))
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
                cs.undo.append(Cleared(plane, removed, was_added))
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
                out = a.undo(self.app, cs)
                if out is Undone.DONE:
                    return None
                if isinstance(out, str):
                    cs.undo.append(a)  # kept: it can be undone once the reason is gone
                    return out
        return "Nothing of yours to undo."
