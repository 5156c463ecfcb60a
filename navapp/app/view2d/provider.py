"""What the 2D view of one tab shows, as the page reads it: its plane, the model's sections
(overlays, computed once per plane and state), the contours drawn on it, the legend and the
targets' distances; and the page's clicks and commands passed on to the drawing. No viser.
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np

from ...anatomy.model import VESSELS
from ..access import OBSERVING, Role
from ..contours import CENTERLINE_OF, contour_pixels
from ..core import Core
from ..drawing import Command, Drawing
from ..imaging import Imaging
from ..palette import DRAWABLE, DRAWN_COLOURS, OVERLAY_STYLE, WORST_POINT
from ..shown import Shown
from .overlays import Overlay, section_pixels

GONE = "This view is no longer connected: reload the page."


class View2D:
    """The ``view2d.http.Provider`` of the viewer."""

    def __init__(self, core: Core, imaging: Imaging, shown: Shown, drawing: Drawing):
        self.core, self.imaging, self.shown, self.drawing = core, imaging, shown, drawing
        self._overlay_cache: dict = {}  # plane index → (plane, geometry, overlays)
        self._image_cache: dict = {}  # (plane index, plane id) → PNG bytes

    def _empty(self, message: str) -> dict:
        return {"etag": "wait", "plane": None, "overlays": [], "contours": [], "drawing": None, "targets": [],
                "legend": [], "message": message}

    def view_state(self, token: str) -> dict | None:
        core, imaging = self.core, self.imaging
        cs = core.state_for(token)
        if cs is None:
            return None
        if core.sd is None or core.session is None:
            return self._empty("Preparing the scene…")
        sd, session = core.sd, core.session
        with core.lock:
            out: dict[str, Any] = {"etag": self.view_etag(token), "plane": None, "width": sd.probe.width_px,
                   "height": sd.probe.height_px, "spacing": sd.probe.spacing_mm, "overlays": [], "contours": [],
                   "drawing": None, "targets": [], "legend": [], "message": cs.message, "feature": cs.feature,
                   "planes": [{"index": i, "label": imaging.label(i)} for i in sorted(core.planes)],
                   "plane_index": cs.plane}
            index = cs.plane
            if index is None or index not in core.planes:
                return out
            plane = core.planes[index]
            out["plane"] = f"Plane {imaging.label(index)}" + \
                (" · added as data" if index in session.planes_added else "")
            out["image_id"] = f"{index}-{id(plane)}"
            contours = [c for c in session.contours if c.plane == index]
            drawing = cs.drawing if cs.drawing in contours else None
            worst = list(core.worst or [])
        out["overlays"] = [ov.to_json() for ov in self.overlays(index)]
        for c in contours:
            if c is drawing:
                continue
            centroid = None
            if c.closed and c.feature in CENTERLINE_OF:
                cols, rows = contour_pixels(c)
                centroid = [float(cols.mean()), float(rows.mean())]
            # the last fit's worst points drawn on this contour: a ring and the residual at the vertex
            # found by its pixel: the index the list was made with named the next vertex once an
            # earlier vertex of the contour had been removed (the ring moved onto a good click)
            flags = [{"v": v, "text": f"{w.residual_mm:.1f} mm" + (" (not used)" if w.rejected else ""),
                      "colour": WORST_POINT} for w in worst
                     if w.origin.contour is c and w.vertex is not None and (v := w.origin.vertex()) is not None]
            out["contours"].append({"feature": c.feature, "colour": DRAWN_COLOURS.get(c.feature, "#fff"),
                                    "vertices": [list(v) for v in c.vertices], "closed": c.closed,
                                    "centroid": centroid, "flags": flags})
        if drawing is not None:
            out["drawing"] = {"feature": drawing.feature, "vertices": [list(v) for v in drawing.vertices]}
        out["legend"] = [{"name": o["name"], "colour": o["colour"]} for o in out["overlays"]] + \
            [{"name": f"drawn {_lower(n)}", "colour": DRAWN_COLOURS[f]} for n, f in DRAWABLE.items()]
        out["targets"] = [line.replace("**", "") for line in self.shown.target_plane_lines(index, short=True)]
        return out

    def view_known(self, token: str) -> bool:
        return self.core.state_for(token) is not None

    def view_etag(self, token: str) -> str | None:
        """What ``view_state`` would call its ETag, without building the state (a poll that
        finds nothing changed costs this only)."""
        core = self.core
        cs = core.state_for(token)
        if cs is None or core.sd is None:
            return None
        with core.lock:
            run = core.run
            return f"{core.version}-{cs.version}-{id(core.result)}-{run.streamed if run else 0}"

    def view_image(self, token: str) -> bytes | None:
        core = self.core
        cs = core.state_for(token)
        if cs is None or cs.plane is None or core.sd is None:
            return None
        plane = core.planes.get(cs.plane)
        if plane is None:
            return None
        key = (cs.plane, id(plane))
        png = self._image_cache.get(key)
        if png is None:
            from PIL import Image

            probe = core.sd.probe
            img = plane.image if plane.image is not None else np.zeros((probe.height_px, probe.width_px), np.uint8)
            buf = io.BytesIO()
            Image.fromarray(np.asarray(img, np.uint8)).save(buf, format="PNG")
            png = self._image_cache[key] = buf.getvalue()
        return png

    def view_click(self, token: str, col: int, row: int, feature: str, plane: int) -> str | None:
        cs = self.core.state_for(token)
        if cs is None:
            return GONE
        if cs.role is Role.OBSERVER:
            return OBSERVING
        return self.drawing.click(cs, col, row, feature, plane)

    def view_command(self, token: str, cmd: str, feature: str, plane: int | None = None) -> str | None:
        cs = self.core.state_for(token)
        if cs is None:
            return GONE
        if cmd == "Plane":
            return None if self.imaging.show(cs, plane) else f"there is no plane {plane}"
        if cs.role is Role.OBSERVER and cmd != Command.FEATURE.value:  # the feature drawn next is the tab's own
            return OBSERVING
        return self.drawing.command(cs, cmd, feature)

    def view_pixel_ratio(self, token: str, ratio: float) -> None:
        """The tab's device pixel ratio as its 2D view's page reports it; a new one lays the
        dock and the framing out again (``ClientView.camera_changed``)."""
        cs = self.core.state_for(token)
        if cs is None or not 0.25 <= ratio <= 8.0 or ratio == cs.pixel_ratio:
            return
        cs.pixel_ratio = ratio
        view = self.core.views.get(cs.client_id)
        if view is not None:
            view.camera_changed()

    def view_going(self, token: str, at_ms: float | None, address: str | None) -> None:
        cs = self.core.state_or_parked(token)  # its viewer connection may have closed already
        if cs is not None:
            self.core.going(cs, at_ms, address)

    def view_resume(self, token: str, previous: str | None, opened_ms: float | None = None,
                    address: str | None = None) -> str | None:
        cs = self.core.state_for(token)
        if cs is None:
            return GONE
        return self.core.resume(cs, previous, opened_ms, address)

    def overlays(self, index: int) -> list[Overlay]:
        """The model's sections with plane ``index``: preoperative (rigidly placed by the
        state on show, as-is before any registration) dashed, registered solid."""
        core = self.core
        sd, _ = core.need_scene()
        geom = self.shown.geometry()
        plane = core.planes[index]
        cached = self._overlay_cache.get(index)
        if cached is not None and cached[0] is plane and cached[1] is geom:  # same plane, same state
            return cached[2]
        T = plane.probe_to_tracker
        probe = sd.probe
        out = []
        rigid = geom.rigid
        place = rigid.apply if rigid is not None else (lambda x: np.asarray(x))
        preop = core.preop
        pre = {n: getattr(preop, n) for n in ("liver", *VESSELS)}
        for name, mesh in pre.items():
            if mesh is not None:
                seg = section_pixels(probe, T, place(mesh.vertices), mesh.faces)
                out.append(Overlay(f"{name} (preop{', rigid' if rigid is not None else ''})",
                                   OVERLAY_STYLE[name][0], True, seg))
        for name, (v, f) in geom.surfaces.items():
            out.append(Overlay(f"{name} (registered)", OVERLAY_STYLE[name][1], False, section_pixels(probe, T, v, f)))
        for t in geom.targets:
            if t.surface is not None:
                out.append(Overlay(f"target {t.name}", OVERLAY_STYLE["target"][1], False,
                                   section_pixels(probe, T, t.surface.vertices, t.surface.faces)))
        self._overlay_cache[index] = (plane, geom, out)
        return out


def _lower(words: str) -> str:
    """A tool's name inside a legend line: "drawn Posterior surface" read as a title; an
    abbreviation (PV, HV) keeps its capitals."""
    return words if words[:2].isupper() else words[:1].lower() + words[1:]
