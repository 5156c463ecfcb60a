"""The 3D scene of one browser and its Layers panel: every object can be shown or hidden
here (per browser: hiding the liver in one tab hides it in no other), standard views, the
error colour scale and a legend floating over the 3D view."""

from typing import Final

import numpy as np
import trimesh
import viser.transforms as vtf

from ...anatomy.model import VESSELS
from ...geometry.transforms import rotation_between
from ..framing import frame, plane_view
from ..motion import Tween
from ..palette import (
    FEATURE_COLOURS,
    LEGEND,
    LIVER,
    REG_TARGET,
    REG_VESSEL,
    REGISTERED,
    SUPPORTS,
    TARGET,
    TRUTH,
    TURBO_CSS,
    VESSEL,
)
from ..state import ERROR_SCALE_MM, Change

HOME_VIEW_MM = np.array([40.0, 260.0, 110.0])  # camera offset from the liver centroid: anterior, a little superior
VIEW_DISTANCE_MM = 280.0
STANDARD_VIEWS = {  # camera direction from the liver centroid (navapp frame: +x left, +y anterior, +z superior)
    "Anterior": (0.0, 1.0, 0.0), "Posterior": (0.0, -1.0, 0.0), "Left": (1.0, 0.0, 0.0), "Right": (-1.0, 0.0, 0.0),
    "Superior": (0.0, 0.01, 1.0),
}
LAYERS = ("Preoperative liver", "Preoperative vessels", "Targets", "Stated supports", "Collected data",
          "Registered liver", "Registered vessels", "Error colours", "True deformed liver (ghost)", "Ultrasound plane",
          "Stylus")
SUPPORT_DOT_MM = 1.0  # the held surface's dots (``show_supports``)
# the error dots' point_size: viser draws a point of size s about 2 s wide (mm); at 1.0 they hid
# a third of the registered vessels' pixels (docs/decisions/viewer.md, "Error dots")
ERROR_DOT_MM = 0.5
# The translucent livers are drawn one-sided, their outer faces only (both are closed and wound
# outward: the imported surface by ``anatomy.cleanup``, the registered one as the mesh's outward
# boundary). Two-sided, three.js draws a translucent mesh twice, inner faces then outer, and every
# tab redraws once a second in software where there is no GPU: the back half of the liver was
# about a third of an idle tab's frame (docs/decisions/viewer.md, "What makes an idle tab redraw").
LIVER_SIDE: Final = "front"
TRUE, PREDICTED = "true error", "predicted error"
ERROR_SOURCES = {TRUE: "true error", PREDICTED: "predicted error, no truth needed"}  # choice → legend label


def wxyz(R):
    return vtf.SO3.from_matrix(np.asarray(R)).wxyz


def error_colours(err, vmax):
    """Per-point RGB (N, 3) uint8 for errors in mm on a fixed scale 0 … vmax (turbo)."""
    from matplotlib import colormaps

    return (colormaps["turbo"](np.clip(np.asarray(err) / max(vmax, 1e-9), 0, 1))[:, :3] * 255).astype(np.uint8)


def stylus_tool() -> trimesh.Trimesh:
    """A stylus in its own frame: tip at the origin, shaft along +z, mm."""
    shaft = trimesh.creation.cylinder(radius=2.5, height=110.0)
    shaft.apply_translation([0, 0, 15.0 + 55.0])
    tip = trimesh.creation.cone(radius=2.5, height=15.0)
    tip.apply_transform(trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0]))
    tip.apply_translation([0, 0, 15.0])
    return trimesh.util.concatenate([shaft, tip])


def probe_body_mm(probe) -> tuple[float, float, float]:
    """The drawn probe's box, mm: its image's width and 6 mm, 12 mm thick, 25 mm behind the face."""
    return (probe.width_px * probe.spacing_mm + 6, 12.0, 25.0)


class LayersPanel:
    def __init__(self, view):
        self.view, self.app, self.core, self.cs = view, view.app, view.app.core, view.cs
        client = view.client
        self.s = client.scene
        g = client.gui
        self.nodes: dict[str, list] = {name: [] for name in LAYERS}
        self.live_lost = False  # the live probe's stream is lost (``lose_live_probe``)
        self.reg: dict = {}
        # the registered nodes move between a run's states rather than jump (``motion``)
        self.tween = Tween(self._draw, view.lock)
        self.data_nodes: dict = {}
        self._supports_shown: object = None  # the stated supports drawn (``show_supports``)
        self._data_shown: dict = {}  # what each data node last showed
        with g.add_folder("Layers and views", expand_by_default=False):
            self.cb = {name: g.add_checkbox(name, name not in ("True deformed liver (ghost)",)) for name in LAYERS}
            self.views = g.add_button_group("View", tuple(STANDARD_VIEWS) + ("Reset",))
            self.scale = g.add_number("Error colour scale, top (mm)", ERROR_SCALE_MM, min=1.0, max=100.0, step=1.0)
            self.source = g.add_dropdown("Error colours show", tuple(ERROR_SOURCES),
                                         hint="the true error (simulated scenes only) or the error predicted "
                                              "from the data and the fit, as in the operating room")
        for cb in self.cb.values():
            cb.on_update(lambda e: self.apply_visibility())
        self.views.on_click(lambda e: self.look(e.target.value))
        self.scale.on_update(lambda e: self._set_scale())
        self.source.on_update(lambda e: self._set_source())
        self.legend_panel = g.add_panel()
        tab = self.legend_panel.add_tab("Legend")
        with tab:
            self.legend = g.add_html("")
        self.legend_panel.float(x=15, y=-15, width=250)
        self._build_preop()
        self._render_legend()

    # ------------------------------------------------------------------ building
    def _add(self, layer, node):
        self.nodes[layer].append(node)
        node.visible = self.cb[layer].value
        return node

    def _build_preop(self):
        preop = self.core.preop
        s = self.s
        shown = self.core.display.of
        self._add("Preoperative liver", s.add_mesh_simple("/preop/liver", *shown(preop.liver),
                                                          color=LIVER, opacity=0.3, side=LIVER_SIDE))
        for name in VESSELS:
            colour = VESSEL[name]
            m = preop.vessel(name)
            if m is not None:
                self._add("Preoperative vessels", s.add_mesh_simple(f"/preop/{name}", *shown(m, vessel=True),
                                                                    color=colour, opacity=0.45))
            cl = preop.centerline(name)
            if cl is not None:
                self._add("Preoperative vessels", s.add_line_segments(
                    f"/preop/{name}_centerline", cl.points[cl.segments()], colour, thickness=2.0,
                    thickness_units="screen"))
        for t in preop.targets:
            if t.surface is not None:
                self._add("Targets", s.add_mesh_simple(f"/preop/targets/{t.name}", t.surface.vertices,
                                                       t.surface.faces, color=TARGET, opacity=0.5))

    def _build_scene(self):
        sd = self.core.sd
        if sd is None:
            return
        s = self.s
        t = sd.truth.get("liver")
        if t is not None and not self.nodes["True deformed liver (ghost)"]:
            self._add("True deformed liver (ghost)", s.add_mesh_simple("/truth/liver", *self.core.display.of(t),
                                                                        color=TRUTH, opacity=0.3))
            self._render_legend()  # the ghost's line only where there is a truth
        if not self.nodes["Stylus"]:
            self.tool = self._add("Stylus", s.add_mesh_trimesh("/stylus/tool", stylus_tool()))
            self.tool.visible = False
            from scipy.spatial import cKDTree

            ref = t if t is not None else self.core.preop.liver
            self._tree, self._normals = cKDTree(ref.vertices), ref.vertex_normals
        if not self.nodes["Ultrasound plane"]:
            probe = sd.probe
            self.probe = self._add("Ultrasound plane", s.add_frame("/probe", show_axes=False))
            self.probe.visible = False
            size = probe_body_mm(probe)
            body = trimesh.creation.box(size)
            body.apply_translation([0, 0, -size[2] / 2])
            s.add_mesh_simple("/probe/body", body.vertices, body.faces, color=(80, 80, 80))
            H, W, sp_ = probe.height_px, probe.width_px, probe.spacing_mm
            # image node axes (x right, y up, z out) = probe (lateral, −depth, elevation)
            R_img = np.column_stack([[1, 0, 0], [0, 0, -1], [0, 1, 0]]).astype(float)
            self.image = s.add_image("/probe/image", np.zeros((H, W, 3), np.uint8), W * sp_, H * sp_,
                                     wxyz=wxyz(R_img), position=(0.0, 0.0, (H - 1) / 2 * sp_))

    # ------------------------------------------------------------------ refresh
    def refresh(self, what):
        core, shown = self.core, self.app.shown
        if what is Change.SCENE and core.sd is not None:
            self._build_scene()
        if what in (Change.SCENE, Change.DATA) and core.sd is not None and core.session is not None:
            self._show_data()
        if what is Change.PLANE:
            self.show_plane()
        if what in (Change.POSE, Change.SCENE, Change.MODEL):
            self.show_supports()
        if what in (Change.RESULT, Change.MODEL):
            if what is Change.MODEL and core.model is not None and core.truth_nodes is None:
                self.source.value, self.source.disabled = PREDICTED, True  # no truth: only the prediction
                self.cs.error_source = "predicted"
                self._render_legend()
            if core.result is not None and core.model is not None:
                self.show_registered(shown.geometry(), shown.surface_error(self.cs), animate=True)
                self._render_legend()  # a result with no prediction says so under the scale
            elif core.result is None:
                for n in self.reg.values():
                    n.visible = False
        self.apply_visibility()

    def show_supports(self):
        """The registration mesh's surface nodes the stated supports hold, as dots on the
        preoperative liver (none while free-floating): the named region, or the surface around
        the points of a support-points file (``mechanics.supports.held_nodes``)."""
        from ...anatomy.meshing import TetMesh
        from ...mechanics.supports import held_nodes

        core = self.core
        with core.lock:
            if core.sd is None or core.session is None or core.model is None:
                return
            held = core.session.stated_supports(core.sd).held
            basis = core.model.basis
        if held == self._supports_shown:
            return
        self._supports_shown = held
        for node in self.nodes["Stated supports"]:
            node.remove()
        self.nodes["Stated supports"].clear()
        if held is not None:
            at = basis.nodes[held_nodes(TetMesh(basis.nodes, basis.tets), held.held, held.release, held.points)]
            self._add("Stated supports", self.s.add_point_cloud("/preop/supports", at.astype(np.float32), SUPPORTS,
                                                                point_size=SUPPORT_DOT_MM))
        self._render_legend()  # its supports line only while some are stated

    def _show_data(self):
        data = self.core.data()
        for name in list(self.data_nodes):
            if name not in data:
                node = self.data_nodes.pop(name)
                self._data_shown.pop(name, None)
                self.nodes["Collected data"].remove(node)
                node.remove()
        for name, pts in data.items():
            if name in self.data_nodes:
                old = self._data_shown.get(name)
                if old is not None and old.shape == pts.shape and np.array_equal(old, pts):
                    continue  # unchanged: nothing sent to the browser (a click changes one feature)
                self.data_nodes[name].points = pts.astype(np.float32)
            else:
                thin = name.endswith("contour") or name == "posterior"
                size = 2.5 if name.endswith("centerline") else 0.6 if thin else 1.2
                self.data_nodes[name] = self._add("Collected data", self.s.add_point_cloud(
                    f"/data/{name}", pts.astype(np.float32), FEATURE_COLOURS.get(name, (255, 255, 255)),
                    point_size=size, precision="float32", point_shape="circle"))
            self._data_shown[name] = pts

    def show_plane(self, plane=None):
        """This browser's plane (or a preview plane) at its tracked pose with its image."""
        core, cs = self.core, self.cs
        sd = core.sd
        if sd is None or not hasattr(self, "probe"):
            return
        live = plane is not None
        if plane is None:
            if cs.plane is None or cs.plane not in core.planes:
                self.probe.visible = False
                return
            plane = core.planes[cs.plane]
        self.live_lost = False  # a fresh frame, or a plane the tab chose
        T = plane.probe_to_tracker
        self.probe.wxyz, self.probe.position = wxyz(T[:3, :3]), T[:3, 3]
        self.probe.visible = self.cb["Ultrasound plane"].value and (live or cs.plane is not None)
        img = plane.image if plane.image is not None else np.zeros((sd.probe.height_px, sd.probe.width_px), np.uint8)
        # viser draws an image's first row at the node's −y edge; flipped, row 0 sits at the probe face
        self.image.image = np.repeat(np.flipud(img)[..., None], 3, axis=2)

    def lose_live_probe(self):
        """The live probe's stream is lost: its plane is hidden until a fresh frame (it stayed at
        its last pose with its last image)."""
        self.live_lost = True
        if hasattr(self, "probe"):
            self.probe.visible = False

    def show_stylus(self, pos):
        if not hasattr(self, "tool"):
            return
        if pos is None:
            self.tool.visible = False
            return
        _, j = self._tree.query(pos)
        self.tool.wxyz = wxyz(rotation_between([0.0, 0.0, 1.0], self._normals[j] + np.array([0.0, 0.3, 0.3])))
        self.tool.position = pos
        self.tool.visible = self.cb["Stylus"].value

    def show_registered(self, geom, error=None, animate=False):
        """The registered liver, vessels, targets and error dots of one state (``StateGeometry``);
        ``error`` (S,) mm at the surface nodes, or None (grey dots). ``animate``: move there
        from what is on screen over ``motion.TWEEN_S`` (a run's states, its answer) rather than
        at once (live re-registration, which follows the tracker)."""
        s = self.s
        surfaces = geom.surfaces
        arrays: dict[str, np.ndarray] = {}  # the new positions of nodes already on screen
        for name, (v, f) in surfaces.items():
            v = np.asarray(v, np.float32)
            if name in self.reg:
                arrays[name] = v
                continue
            if name == "liver":
                node = s.add_mesh_simple("/registered/liver", v, f, color=REGISTERED, opacity=0.4,
                                        side=LIVER_SIDE)
                self._add("Registered liver", node)
            else:
                self._add("Registered vessels", s.add_mesh_simple(f"/registered/{name}", v, f,
                                                                  color=REG_VESSEL[name]))
            self.reg[name] = node if name == "liver" else self.nodes["Registered vessels"][-1]
            self.tween.note(name, v)
        for t in geom.targets:
            if t.surface is None:
                continue
            key, v = f"target:{t.name}", np.asarray(t.surface.vertices, np.float32)
            if key in self.reg:
                arrays[key] = v
            else:
                self.reg[key] = self._add("Targets", s.add_mesh_simple(f"/registered/targets/{t.name}", v,
                                                                      t.surface.faces, color=REG_TARGET))
                self.tween.note(key, v)
        if "liver" in surfaces and (error is not None or "error" in self.reg):
            # no error for this state (a prediction comes with the result): grey dots, never stale colours
            pts = np.asarray(surfaces["liver"][0], np.float32)
            self._last_error = (pts, error)
            if "error" in self.reg:
                arrays["error"] = pts
            self._show_error()
        moving = self.tween.to(arrays) if animate else self.tween.stop()
        for name, a in arrays.items():
            if name not in moving:
                self._put(name, a)
        self.apply_visibility()

    def _put(self, name: str, a: np.ndarray):
        """Positions of one registered node on screen now (not sent again when unchanged)."""
        if self.tween.shows(name, a):
            return
        self._draw({name: a})
        self.tween.note(name, a)

    def _draw(self, frame: dict[str, np.ndarray]):
        for name, a in frame.items():
            node = self.reg.get(name)
            if node is None:
                continue
            if name == "error":
                node.points = a
            else:
                node.vertices = a

    def _show_error(self):
        """The error dots' colours (their positions move with the liver)."""
        pts, err = self._last_error
        colours = error_colours(err, self.cs.error_scale_mm) if err is not None else \
            np.full((len(pts), 3), 170, np.uint8)
        if "error" in self.reg:
            self.reg["error"].colors = colours
        else:
            self.reg["error"] = self._add("Error colours", self.s.add_point_cloud(
                "/registered/error", pts, colours, point_size=ERROR_DOT_MM, precision="float32",
                point_shape="circle"))
            self.tween.note("error", pts)

    def _set_source(self):
        self.cs.error_source = "predicted" if self.source.value == PREDICTED else "true"
        core, shown = self.core, self.app.shown
        if core.result is not None and core.model is not None and core.run is None:
            self.show_registered(shown.geometry(), shown.surface_error(self.cs))
        self._render_legend()

    def _set_scale(self):
        self.cs.error_scale_mm = float(self.scale.value)
        if getattr(self, "_last_error", None) is not None:
            self._show_error()
        self._render_legend()

    def apply_visibility(self):
        for layer, nodes in self.nodes.items():
            on = self.cb[layer].value
            for n in nodes:
                if layer == "Stylus":
                    n.visible = on and (self.app.stylus.tip is not None or self.app.live.tip is not None)
                elif layer == "Ultrasound plane":
                    n.visible = on and not self.live_lost and (self.cs.plane is not None
                                                               or self.app.live.link is not None)
                else:
                    n.visible = on

    def look(self, name):
        """A standard view ("Reset": the home view), framed for this tab's window when it is
        known (``framing``: the liver whole, centred between the panels)."""
        cam = self.view.client.camera
        c = self.core.centre
        cam.up_direction = (0.0, 0.0, 1.0)
        cam.near, cam.far = 1.0, 5000.0
        d = HOME_VIEW_MM if name == "Reset" else np.asarray(STANDARD_VIEWS[name], float)
        screen = self.view.screen
        if screen is not None:
            position, target = frame(self.core.preop.liver.vertices[::5], d, (0.0, 0.0, 1.0), float(cam.fov), screen)
        else:
            position = c + (HOME_VIEW_MM if name == "Reset" else d / np.linalg.norm(d) * VIEW_DISTANCE_MM)
            target = c
        cam.position = position  # viser moves look_at with position, so the target is set second
        cam.look_at = target

    def look_at_plane(self, T):
        """An oblique view onto a plane: from its front, a little above; framed for this tab's
        window when it is known (``framing.plane_view``: the liver whole, between the panels)."""
        cam = self.view.client.camera
        cam.up_direction = (0.0, 0.0, 1.0)
        probe = self.core.sd.probe if self.core.sd is not None else None
        position, centre = plane_view(T, self.core.preop.liver.vertices[::5], float(cam.fov), self.view.screen,
                                      probe_body_mm(probe) if probe is not None else (0.0, 0.0, 0.0))
        cam.position = position  # viser moves look_at with position, so the target is set second
        cam.look_at = centre

    def _render_legend(self):
        vmax = self.cs.error_scale_mm
        res = self.core.result
        # a pose not to be believed has no predicted error (``shown.Shown.predict``): grey, and why
        none = (self.source.value == PREDICTED and res is not None and res.predicted_mm is None
                and res.pose_warning is not None)
        sw = "".join(
            f"<div><span style='display:inline-block;width:12px;height:12px;background:rgb{e.colour};"
            f"margin-right:5px;opacity:{e.opacity}'></span>{e.words}</div>"
            for e in LEGEND if e.layer is None or self.nodes[e.layer])
        self.legend.content = (
            f"<div style='font-size:12px'>{sw}<div style='margin-top:6px'>{ERROR_SOURCES[self.source.value]} "
            f"(dots on the registered surface)</div>"
            f"<div style='height:10px;background:linear-gradient(to right,{TURBO_CSS})'></div>"
            f"<div style='display:flex;justify-content:space-between'><span>0</span><span>{vmax / 2:g}</span>"
            f"<span>{vmax:g} mm</span></div>"
            + ("<div style='margin-top:4px;color:#b00'>none on show: the pose is not to be believed (grey dots)</div>"
               if none else "") + "</div>")
