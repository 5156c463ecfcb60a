"""The ultrasound planes of a session: the one each tab shows, adding a plane's simulated
segmentation as data, placing the probe by hand (a new plane acquired at that pose), the
suggested next plane, and the planes' names. No viser here.

Plane indices: the scene's preset planes from 0, planes placed by hand from
``FREE_PLANE_BASE``, frozen tracked frames from ``live.LIVE_PLANE_BASE``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..simulation.scenedata import acquire_free_plane
from ..simulation.ultrasound import PlaneData
from .actions import Act
from .core import Core
from .palette import VESSEL_SHORT, feature_words
from .session import Session
from .state import Action, Change, ClientState, Undone

FREE_PLANE_BASE = 100  # indices of planes placed by hand start here
LIVE_PLANE_BASE = 1000  # indices of frozen live frames start here


@dataclass
class PlaneAdded(Action):
    session: Session
    plane: int

    def undo(self, cs):
        if self.plane not in self.session.planes_added:
            return Undone.GONE
        self.session.planes_added.remove(self.plane)
        return Undone.DONE


@dataclass
class FreePlanePlaced(Action):
    core: Core
    plane: int

    def undo(self, cs):
        session = self.core.need_session()
        if any(c.plane == self.plane for c in session.contours) or self.plane in session.planes_added:
            return "That free plane has contours or data on it now; clear it first."
        session.free_planes = [f for f in session.free_planes if f["index"] != self.plane]
        self.core.planes.pop(self.plane, None)
        if cs.plane == self.plane:
            cs.plane = None
        return Undone.DONE


class Imaging:
    def __init__(self, core: Core, following: Callable[[], bool]):
        self.core = core
        self.following = following  # live re-registration is on (``live.Live.following``)

    def label(self, i: int) -> str:
        p = self.core.planes[i]
        if p.orientation == "live":
            return f"live {i - LIVE_PLANE_BASE + 1} (tracked frame)"
        vessels = sorted({VESSEL_SHORT[f] for f in p.features if f in VESSEL_SHORT})
        what = ", ".join(vessels) if vessels else "no vessel"
        name = f"{i + 1} ({p.orientation})" if i < FREE_PLANE_BASE else f"free {i - FREE_PLANE_BASE + 1}"
        return f"{name} — {what}"

    def from_label(self, label: str) -> int | None:
        return next((i for i in self.core.planes if self.label(i) == label), None)

    def show(self, cs: ClientState, index: int | None) -> bool:
        core = self.core
        if index is None or index not in core.planes:
            return False
        with core.lock:
            cs.plane = index
            if cs.drawing is not None and cs.drawing.plane != index:
                cs.left[cs.drawing.plane] = cs.drawing
                cs.drawing = None  # an unfinished contour stays as drawn (an open line) on its own plane
            back = cs.left.pop(index, None)
            if cs.drawing is None and back is not None and not back.closed and back in core.need_session().contours:
                # back on a plane left mid-contour: the next click continues it (a new contour
                # there left the old one as an open line nobody meant to draw)
                cs.drawing = back
            cs.touch()
        core.save_tabs()  # the plane the tab shows is its own work too
        core.refresh_view(cs, Change.PLANE)
        return True

    def add(self, cs: ClientState) -> str | None:
        """The simulated segmentation of this browser's plane becomes data."""
        core = self.core
        session = core.need_session()
        if cs.plane is None:
            return "Choose a plane first."
        with core.lock:
            if cs.plane in session.planes_added:
                return None
            session.planes_added.append(cs.plane)
            cs.undo.append(PlaneAdded(session, cs.plane))
        core.changed(Change.DATA)
        core.record(cs, Act.PLANE, self.label(cs.plane))
        return None

    def place_probe(self, cs: ClientState, T) -> int:
        """Acquire a new plane at a hand-placed pose (kept in the session); returns its index."""
        core = self.core
        session = core.need_session()
        plane = self.acquire_at(T)
        with core.lock:
            index = FREE_PLANE_BASE + len(session.free_planes)
            while index in core.planes:
                index += 1
            plane.index = index
            core.planes[index] = plane
            session.free_planes.append({"index": index, "pose": np.asarray(T).tolist()})
            cs.undo.append(FreePlanePlaced(core, index))
        self.show(cs, index)
        core.changed(Change.DATA)
        core.record(cs, Act.FREE_PLANE, f"plane {index} at {np.round(np.asarray(T)[:3, 3], 1).tolist()} mm")
        return index

    def acquire_at(self, T, index: int | None = None) -> PlaneData:
        """A simulated plane at pose T (4×4), not kept: the free probe's preview."""
        sd, session = self.core.need_scene()
        i = index if index is not None else FREE_PLANE_BASE + len(session.free_planes)
        return acquire_free_plane(sd, i, np.asarray(T, float))

    def suggest(self, cs: ClientState, on_done) -> str | None:
        """Rank candidate probe poses by the expected drop of the mean predicted error
        (``registration.next_plane``) in the worker thread; the best is acquired as this
        tab's plane and ``on_done(message)`` says what was suggested."""
        from ..registration.next_plane import suggest_planes
        from .worker import viewer_options

        core = self.core
        reg = core.last_reg
        if reg is None or reg.libr is None or not reg.data_model_frame:
            return "Register deformably first: the suggestion ranks planes by what they would add to a fit."
        if self.following():
            return "Live re-registration is on: switch it off first."

        # ranked by the tumours where there are any: the organ's mean had picked planes 50–57 mm
        # from both tumours of the demo
        centres = np.array([t.centre for t in core.preop.targets]) if core.preop.targets else None

        def job(cancel):
            try:
                return suggest_planes(reg, preop=core.preop, points=centres, points_name="the tumours (centres)",
                                      weights=viewer_options().weights)  # the fit's own weighting
            except Exception as exc:  # said in the panel; the button comes back
                return f"No suggestion: {exc.__class__.__name__}: {exc}"

        def done(sug):
            if isinstance(sug, str) or not sug.candidates:
                on_done(sug if isinstance(sug, str) else "No candidate pose on the anterior surface.")
                return
            best = sug.best
            with core.lock:  # suggested again at the same pose (unchanged fit): show that plane, make no copy
                same = [i for i, p in core.planes.items() if i >= FREE_PLANE_BASE and p.orientation == "free"
                        and np.allclose(p.probe_to_tracker, best.pose, atol=1e-6)]
            if same:
                index = same[0]
                self.show(cs, index)
            else:
                index = self.place_probe(cs, best.pose)
            o = best.pose[:3, 3]
            feats = ", ".join(feature_words(f) for f in sorted(best.features)) or "nothing"
            on_done(f"Suggested: a {best.orientation} plane with its probe face at ({o[0]:.0f}, {o[1]:.0f}, "
                    f"{o[2]:.0f}) mm (now {self.label(index)}), expected to show {feats}; mean predicted "
                    f"error at {sug.over} {sug.current_mean_mm:.2f} → "
                    f"{best.predicted_mean_mm:.2f} mm. "
                    f"{len(sug.candidates)} poses ranked by {sug.over} in {sug.seconds:.1f} s. Add its segmentation or "
                    "draw on it.")

        ok = core.worker is not None and core.worker.submit(job, done)
        return None if ok else "A registration is running; try again when it has finished."
