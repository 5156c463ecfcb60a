"""The Ultrasound panel: this browser's plane, its simulated segmentation, the free probe
with a live preview and pose readout, and the 2D view (``view2d``) docked beside the 3D
view, where contours are drawn."""

import threading

import numpy as np
import viser.transforms as vtf

from ...geometry.transforms import homogeneous
from ..drawing import Command
from ..framing import DOCK_2D_PX
from ..palette import DRAWABLE, data_counts
from ..state import Change
from .layers import wxyz

IFRAME_H = 860


class UltrasoundPanel:
    def __init__(self, view):
        self.view, self.app, self.core, self.cs = view, view.app, view.app.core, view.cs
        g = view.client.gui
        with g.add_folder("Ultrasound"):
            self.plane_dd = g.add_dropdown("Plane", ("—",), disabled=True)
            self.btn_add = g.add_button("Add this plane's segmentation (simulated)", disabled=True)
            self.cb_2d = g.add_checkbox("2D view (draw here)", True)
            self.feature = g.add_dropdown("Draw", tuple(DRAWABLE))
            self.cmds = g.add_button_group("Contour", tuple(c.value for c in Command if c is not Command.FEATURE))
            self.btn_suggest = g.add_button("Suggest the next plane",
                                            hint="ranks probe poses on the registered anterior surface by how much "
                                                 "each plane is expected to lower the predicted error")
            self.suggestion = g.add_markdown("")
            self.cb_free = g.add_checkbox("Place probe freely", False, disabled=True)
            self.pose_md = g.add_markdown("")
            self.info = g.add_markdown("")
            self.dist = g.add_markdown("")
        self.plane_dd.on_update(lambda e: self._choose())
        self.btn_add.on_click(view.edits(lambda e: self._msg(self.app.imaging.add(self.cs))))
        self.cb_2d.on_update(lambda e: self._show_2d(self.cb_2d.value))
        self.feature.on_update(lambda e: self.app.drawing.command(self.cs, Command.FEATURE.value, self.feature.value))
        self.cmds.on_click(view.edits(lambda e: self._msg(self.app.drawing.command(self.cs, e.target.value,
                                                                                      self.feature.value))))
        self.cb_free.on_update(view.edits(lambda e: self._free_probe(self.cb_free.value)))
        self.btn_suggest.on_click(view.edits(lambda e: self._suggest()))
        self.panel = g.add_panel()
        tab = self.panel.add_tab("Ultrasound image")
        url = view.app.view2d.page_url(self.cs.token, view.app.view2d_host, view.app.access.token_for(self.cs.role))
        with tab:
            self.frame = g.add_html(f"<iframe src='{url}' title='ultrasound 2D view' "
                                    f"style='width:100%;height:{IFRAME_H}px;border:0'></iframe>")
        self.panel.dock_left()
        self.panel.set_width(DOCK_2D_PX[0])  # narrower once the window's width is known (``ClientView``)
        self.gizmo = None
        self._preview_T = None
        self._preview_busy = threading.Lock()

    def _msg(self, err):
        if err:
            self.view.notify("Ultrasound", err)

    def _choose(self):
        i = self.app.imaging.from_label(self.plane_dd.value)
        if i is not None and i != self.cs.plane:
            self.app.imaging.show(self.cs, i)

    def _suggest(self):
        self.suggestion.content = "Ranking candidate planes…"
        self.btn_suggest.disabled = True

        def done(message):
            self.suggestion.content = message
            self.btn_suggest.disabled = False
            planes = self.core.planes
            if message.startswith("Suggested") and self.cs.plane in planes:
                self.view.layers.look_at_plane(planes[self.cs.plane].probe_to_tracker)

        err = self.app.imaging.suggest(self.cs, done)
        if err:
            self.suggestion.content = ""
            self.btn_suggest.disabled = False
            self.view.notify("Ultrasound", err)

    def _show_2d(self, on):
        if on:
            self.panel.expand()
        else:
            self.panel.minimize()

    def dock(self, width_px: int):
        self.panel.set_width(width_px)

    def open_2d(self):
        self.cb_2d.value = True
        self.panel.expand()

    def refresh(self, what):
        core, cs, imaging, shown = self.core, self.cs, self.app.imaging, self.app.shown
        sd, session, planes = core.sd, core.session, core.planes
        if sd is None or session is None:
            return
        if what in (Change.RESULT, Change.MODEL, Change.RUN) and cs.plane is not None and cs.plane in planes:
            self.dist.content = "  \n".join(shown.target_plane_lines(cs.plane))
        if what in (Change.SCENE, Change.DATA, Change.PLANE):
            labels = tuple(imaging.label(i) for i in sorted(planes)) or ("—",)
            if tuple(self.plane_dd.options) != labels:
                self.plane_dd.options = labels
            self.plane_dd.disabled = not planes
            self.btn_add.disabled = cs.plane is None
            self.cb_free.disabled = False
            if cs.plane is not None and cs.plane in planes:
                label = imaging.label(cs.plane)
                if self.plane_dd.value != label:
                    self.plane_dd.value = label
            if self.feature.value != cs.feature:
                self.feature.value = cs.feature
            with core.lock:
                added = [imaging.label(i) for i in session.planes_added]
                drawn = [c for c in session.contours if c.vertices]
                data = session.data(sd, planes)
            counts = data_counts(data)
            self.info.content = (f"Planes added as data: {', '.join(added) if added else 'none'}.  \n"
                                 f"Contours drawn: {len(drawn)} ({sum(c.closed for c in drawn)} closed).  \n"
                                 f"Data points: {counts}")
            if cs.plane is not None:
                self.dist.content = "  \n".join(shown.target_plane_lines(cs.plane))
        if what is Change.PLANE and cs.plane is not None and cs.plane in planes:
            if not self.cb_2d.value:
                self.cb_2d.value = True
            self.panel.expand()
            self.view.layers.show_plane()
            T = planes[cs.plane].probe_to_tracker
            if self.gizmo is not None:
                self.gizmo.wxyz, self.gizmo.position = wxyz(T[:3, :3]), T[:3, 3]
            self._pose(T)

    # ------------------------------------------------------------------ free probe
    def _free_probe(self, on):
        imaging, cs, planes = self.app.imaging, self.cs, self.core.planes
        if not on:
            if self.gizmo is not None:
                self.gizmo.remove()
                self.gizmo = None
            return
        if cs.plane is None:
            imaging.show(cs, min(planes))
        if cs.plane is None:
            return
        T = planes[cs.plane].probe_to_tracker
        # drawn over the liver (no depth test), so it can be grabbed where the probe is
        self.gizmo = self.view.client.scene.add_transform_controls("/gizmo", scale=40.0, depth_test=False,
                                                                   wxyz=wxyz(T[:3, :3]), position=T[:3, 3])

        @self.gizmo.on_update
        def _(event):
            T = self._gizmo_pose()
            self._pose(T)
            self._preview_T = T
            if self._preview_busy.acquire(blocking=False):
                threading.Thread(target=self._preview, daemon=True).start()

        @self.gizmo.on_drag_end
        def _(event):
            self._preview_T = None
            imaging.place_probe(cs, self._gizmo_pose())

    def _gizmo_pose(self):
        gizmo = self.gizmo
        assert gizmo is not None  # called from the gizmo's own callbacks
        return homogeneous(vtf.SO3(np.asarray(gizmo.wxyz)).as_matrix(), gizmo.position)

    def _preview(self):
        """Simulate the image under the moving probe, latest pose wins."""
        try:
            while self._preview_T is not None:
                T = self._preview_T
                plane = self.app.imaging.acquire_at(T)
                if self._preview_T is None:
                    break
                self.view.layers.show_plane(plane)
                if self._preview_T is T:
                    break
        finally:
            self._preview_busy.release()

    def _pose(self, T):
        p = T[:3, 3]
        n = T[:3, 1]
        d = T[:3, 2]
        self.pose_md.content = (f"Probe face at ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm; "
                                f"depth axis ({d[0]:+.2f}, {d[1]:+.2f}, {d[2]:+.2f}), "
                                f"plane normal ({n[0]:+.2f}, {n[1]:+.2f}, {n[2]:+.2f})")
