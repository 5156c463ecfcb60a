"""``navapp serve``: the viser web viewer. The only module that imports viser.

The viewer opens at once on the preoperative anatomy; a start-up thread then simulates the
scene (cached), restores the session and computes the basis (cached), reporting progress in
the panel. Registrations and settings sweeps run in the worker thread (``worker.py``); the
stylus sweep runs in its own animation thread. Every change to the user's data is written
to the session folder at once (``session.py``).
"""

import threading
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import trimesh
import viser
import viser.transforms as vtf

from .. import progress
from ..anatomy.phantom import make_phantom
from ..errors import NavappError
from ..evaluation.cost import lm_sweep, pareto_front
from ..registration.pipeline import deform_points, prepare
from .contours import DRAWABLE, Contour, click_to_pixel
from .guide import STEPS
from .scenedata import acquire_free_plane, load_scene_data
from .session import default_folder, export, open_session
from .worker import RegistrationWorker

LIVER = (205, 160, 140)
PORTAL = (220, 50, 50)
HEPATIC = (60, 90, 220)
TRUTH = (60, 200, 90)
REGISTERED = (240, 190, 60)
FEATURE_COLOURS = {
    "anterior": (255, 255, 255), "falciform": (255, 0, 255), "ridge_left": (0, 255, 255), "ridge_right": (0, 200, 200),
    "posterior": (255, 200, 0), "portal_contour": (255, 80, 80), "hepatic_contour": (90, 140, 255),
    "portal_centerline": (255, 0, 0), "hepatic_centerline": (0, 60, 255),
}
STYLUS_MM_PER_S = 40.0  # a steady sweep of the tip, at "1×"
FRAME_S = 0.05
FREE_PLANE_BASE = 100  # indices of planes placed by hand start here
HOME_VIEW_MM = np.array([40.0, 260.0, 110.0])  # camera offset from the liver centroid: anterior, a little superior
DRAWING_FOV_DEG = 60.0  # vertical field of view of the drawing view
DRAWING_DISTANCE_MM = 110.0  # camera to image in the drawing view: the 80 mm-deep image fills ~half the height


def _wxyz(R):
    return vtf.SO3.from_matrix(np.asarray(R)).wxyz


def _rotation_z_to(n):
    """A rotation taking +z to the unit vector n."""
    z = np.asarray(n, float) / np.linalg.norm(n)
    a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def error_colours(err, vmax):
    """Per-vertex RGBA (V, 4) uint8 for errors in mm, blue (0) → red (vmax) via matplotlib's turbo."""
    from matplotlib import colormaps

    return (colormaps["turbo"](np.clip(err / max(vmax, 1e-9), 0, 1)) * 255).astype(np.uint8)


def stylus_tool() -> trimesh.Trimesh:
    """A stylus in its own frame: tip at the origin, shaft along +z, mm."""
    shaft = trimesh.creation.cylinder(radius=2.5, height=110.0)
    shaft.apply_translation([0, 0, 15.0 + 55.0])
    tip = trimesh.creation.cone(radius=2.5, height=15.0)
    tip.apply_transform(trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0]))
    tip.apply_translation([0, 0, 15.0])
    return trimesh.util.concatenate([shaft, tip])


class App:
    def __init__(self, scene, host="127.0.0.1", port=8080, session_dir=None, edge=4.0, k=45, cache_root=None):
        self.scene, self.edge, self.k, self.cache_root = scene, edge, k, cache_root
        self.session_dir = session_dir
        self.server = viser.ViserServer(host=host, port=port, label="navapp", verbose=False)
        self.url = f"http://{self.server.get_host()}:{self.server.get_port()}"
        self.lock = threading.RLock()
        self.sd = None
        self.session = None
        self.planes = {}
        self.model = None
        self.worker = None
        self.current_plane = None
        self.current = None  # the contour being drawn
        self.step = 0
        self.stylus_thread = None
        self.stylus_stop = threading.Event()
        self.run_trace = []  # (seconds, error mm or Ω) of the running registration
        self.run_label = ""
        self.streamed = 0
        self.truth_nodes = None
        self.last_error = None
        self.n_reg = {}  # registered model in the scene: "liver", "portal", "hepatic", "error"
        self._build_gui()
        self._show_preop()
        threading.Thread(target=self._start_up, daemon=True).start()

    # ------------------------------------------------------------------ layout
    def _build_gui(self):
        g = self.server.gui
        g.configure_theme(control_width="large", dark_mode=False)
        self.status = g.add_markdown("**Starting…**")
        self.bar = g.add_progress_bar(0.0, animated=True)
        with g.add_folder("Guided demo"):
            self.guide_md = g.add_markdown("")
            self.guide_btn = g.add_button("", color="green")
            self.guide_nav = g.add_button_group("Step", ("◀ Back", "Skip ▶"))
        with g.add_folder("Scene", expand_by_default=False):
            self.cb_preop = g.add_checkbox("Preoperative liver", True)
            self.cb_vessels = g.add_checkbox("Vessels", True)
            self.cb_truth = g.add_checkbox("True deformed liver (ghost)", False)
            self.cb_registered = g.add_checkbox("Registered model", True)
            self.cb_error = g.add_checkbox("Colour by error", True)
        with g.add_folder("Stylus"):
            self.stylus_md = g.add_markdown("0 points digitised")
            self.stylus_speed = g.add_slider("Speed (× realistic)", 1.0, 20.0, 1.0, 5.0)
            self.btn_stylus = g.add_button("Digitise anterior surface", disabled=True)
            self.btn_stylus_all = g.add_button("Collect the whole sweep now", disabled=True)
        with g.add_folder("Ultrasound"):
            self.plane_dd = g.add_dropdown("Plane", ("—",), disabled=True)
            self.btn_auto = g.add_button("Auto-segment this plane (simulation)", disabled=True)
            self.cb_free = g.add_checkbox("Place probe freely", False, disabled=True)
            self.draw_feature = g.add_dropdown("Draw", tuple(DRAWABLE))
            self.cb_draw = g.add_checkbox("Click on image adds vertices", False, disabled=True)
            self.btn_view = g.add_button("Drawing view (face-on)", disabled=True)
            self.draw_btns = g.add_button_group("Contour", ("Close", "Finish line", "Undo", "Clear plane"))
            self.plane_md = g.add_markdown("")
        with g.add_folder("Registration"):
            self.btn_rigid = g.add_button("Rigid", disabled=True)
            self.btn_surface = g.add_button("Deformable (surface only)", disabled=True)
            self.btn_all = g.add_button("Deformable (all data)", disabled=True)
            self.btn_warm = g.add_button("Re-register (warm start)", disabled=True)
            self.btn_cancel = g.add_button("Cancel", color="red", disabled=True)
            self.reg_md = g.add_markdown("")
            self.plot = g.add_uplot((np.zeros(2), np.zeros(2)),
                                    ({"label": "seconds"}, {"label": "error (mm)", "stroke": "#d33", "width": 2}),
                                    title="Error against time", aspect=1.6, scales={"x": {"time": False}})
            self.log_md = g.add_markdown("")
        with g.add_folder("What accuracy costs", expand_by_default=False):
            g.add_markdown("Reruns the current data with the LM iteration cap and the stopping tolerance "
                           "varied; each point is one registration (★ = Pareto front).")
            self.btn_sweep = g.add_button("Sweep settings", disabled=True)
            self.cost_plot = g.add_uplot((np.zeros(1), np.zeros(1)),
                                         ({"label": "seconds"}, {"label": "TRE (mm)", "stroke": "#36c", "width": 0,
                                                                 "points": {"show": True, "size": 8}}),
                                         title="TRE against registration time", aspect=1.6,
                                         scales={"x": {"time": False}})
            self.cost_md = g.add_markdown("")
        with g.add_folder("Session"):
            self.session_md = g.add_markdown("")
            self.btn_export = g.add_button("Export (PLY, VTK, CSV)", disabled=True)
        self._wire()
        self._show_step()

    def _wire(self):
        self.guide_btn.on_click(lambda e: self._guide_action(e))
        self.guide_nav.on_click(lambda e: self._guide_nav(e.target.value))
        for cb in (self.cb_preop, self.cb_vessels, self.cb_truth, self.cb_registered, self.cb_error):
            cb.on_update(lambda e: self._visibility())
        self.btn_stylus.on_click(lambda e: self.start_stylus())
        self.btn_stylus_all.on_click(lambda e: self.collect_stylus_now())
        self.plane_dd.on_update(lambda e: self.show_plane(self._plane_from_label(self.plane_dd.value)))
        self.btn_auto.on_click(lambda e: self.auto_segment())
        self.cb_free.on_update(lambda e: self._free_probe(self.cb_free.value))
        self.btn_view.on_click(lambda e: self.drawing_view(e.client))
        self.draw_btns.on_click(lambda e: self._contour_command(e.target.value))
        self.btn_rigid.on_click(lambda e: self.register("rigid"))
        self.btn_surface.on_click(lambda e: self.register("surface"))
        self.btn_all.on_click(lambda e: self.register("all"))
        self.btn_warm.on_click(lambda e: self.register("warm"))
        self.btn_cancel.on_click(lambda e: self.worker and self.worker.cancel())
        self.btn_sweep.on_click(lambda e: self.sweep())
        self.btn_export.on_click(lambda e: self.export())

    # ------------------------------------------------------------------ messages
    def notify(self, title, body, error=False):
        for client in self.server.get_clients().values():
            client.add_notification(title, body, color="red" if error else None, auto_close_seconds=None if error else 6.0)

    def _status(self, text, fraction=None):
        self.status.content = text
        if fraction is None:
            self.bar.animated = True
            self.bar.value = 100.0
        else:
            self.bar.animated = False
            self.bar.value = 100.0 * fraction

    # ------------------------------------------------------------------ start-up
    def _show_preop(self):
        preop = make_phantom(self.scene.phantom) if self.scene.phantom is not None else None
        if preop is None:
            from ..anatomy.caseio import read_case

            preop = read_case(self.scene.case).preop
        self.preop = preop
        s = self.server.scene
        s.set_up_direction("+z")
        self.centre = preop.liver.vertices.mean(0)
        cam = self.server.initial_camera
        cam.up_direction, cam.near, cam.far = (0.0, 0.0, 1.0), 1.0, 5000.0
        cam.look_at, cam.position = self.centre, self.centre + HOME_VIEW_MM
        self.n_liver = s.add_mesh_simple("/preop/liver", preop.liver.vertices, preop.liver.faces, color=LIVER,
                                         opacity=0.35, side="double")
        self.n_vessels = []
        for name, colour in (("portal", PORTAL), ("hepatic", HEPATIC)):
            m = preop.vessel(name)
            if m is not None:
                self.n_vessels.append(s.add_mesh_simple(f"/preop/{name}", m.vertices, m.faces, color=colour))
            cl = preop.centerline(name)
            if cl is not None:
                self.n_vessels.append(s.add_line_segments(f"/preop/{name}_centerline", cl.points[cl.segments()],
                                                          colour, thickness=2.0, thickness_units="screen"))

    def _frame_camera(self, client):
        client.camera.up_direction = (0.0, 0.0, 1.0)
        client.camera.far = 5000.0
        client.camera.near = 1.0
        client.camera.position = self.centre + HOME_VIEW_MM
        client.camera.look_at = self.centre

    def _start_up(self):
        listener = progress.add_listener(lambda d, f: self._status(f"**Preparing:** {d}", f))
        try:
            self._status("**Preparing:** simulating the intraoperative scene (cached after the first start)")
            self.sd = load_scene_data(self.scene, self.cache_root, self.edge)
            folder = Path(self.session_dir) if self.session_dir else default_folder(self.sd)
            self.session, self.planes = open_session(folder, self.sd)
            self._show_scene_data()
            self._status("**Preparing:** registration model (mesh, basis; cached after the first start)")
            self.model, _ = prepare(self.sd.case, self.edge, self.k, self.cache_root)
            x0 = self.sd.case.targets[:, :3] if self.sd.case.targets is not None else None
            if x0 is not None and x0.shape == self.model.basis.nodes.shape and np.allclose(x0, self.model.basis.nodes):
                self.truth_nodes = self.sd.case.targets[:, 3:]
            self.worker = RegistrationWorker(self.model, self._on_update, self._on_done, self._on_error, max_rate_hz=20.0)
            for b in (self.btn_rigid, self.btn_surface, self.btn_all, self.btn_sweep, self.btn_export):
                b.disabled = False
            self._status(f"**Ready.** {len(self.model.basis.nodes):,} nodes, k = {self.k}. "
                         f"Session: `{self.session.folder}`", 1.0)
            self.bar.visible = False
            self._show_step()
        except NavappError as exc:
            self._status(f"**Error:** {exc}", 0.0)
            self.notify("navapp", str(exc), error=True)
        except Exception as exc:  # shown, not lost in a thread
            self._status(f"**Error while starting:** {exc.__class__.__name__}: {exc}", 0.0)
            self.notify("navapp", f"{exc.__class__.__name__}: {exc}", error=True)
            raise
        finally:
            progress.remove_listener(listener)

    def _show_scene_data(self):
        s, sd = self.server.scene, self.sd
        t = sd.truth["liver"]
        self.n_truth = s.add_mesh_simple("/truth/liver", t.vertices, t.faces, color=TRUTH, opacity=0.3,
                                         visible=self.cb_truth.value)
        self.truth_normals = t.vertex_normals
        from scipy.spatial import cKDTree

        self.truth_tree = cKDTree(t.vertices)
        self.n_tool = s.add_mesh_trimesh("/stylus/tool", stylus_tool(), visible=False)
        self.n_data = {}
        # probe: a frame at the tracked pose; the image plane is its child
        self.n_probe = s.add_frame("/probe", show_axes=False, visible=False)
        body = trimesh.creation.box((sd.probe.width_px * sd.probe.spacing_mm + 6, 12.0, 25.0))
        body.apply_translation([0, 0, -12.5])
        s.add_mesh_simple("/probe/body", body.vertices, body.faces, color=(80, 80, 80))
        blank = np.zeros((sd.probe.height_px, sd.probe.width_px, 3), np.uint8)
        H, W, sp_ = sd.probe.height_px, sd.probe.width_px, sd.probe.spacing_mm
        # image node axes (x right, y up, z out) = probe (lateral, −depth, elevation)
        R_img = np.column_stack([[1, 0, 0], [0, 0, -1], [0, 1, 0]]).astype(float)
        self.n_image = s.add_image("/probe/image", blank, W * sp_, H * sp_, wxyz=_wxyz(R_img),
                                   position=(0.0, 0.0, (H - 1) / 2 * sp_))
        self.n_image.on_click(self._image_clicked)
        self.n_drawn = None
        labels = self._plane_labels()
        self.plane_dd.options = labels
        self.plane_dd.disabled = not self.planes
        for w in (self.btn_stylus, self.btn_stylus_all, self.btn_auto, self.cb_free, self.cb_draw, self.btn_view):
            w.disabled = False
        self._refresh_data()
        self._refresh_log()

    # ------------------------------------------------------------------ data display
    def _plane_labels(self):
        return tuple(self._label_of(i) for i in sorted(self.planes)) or ("—",)

    def _plane_from_label(self, label):
        if label.startswith("free "):
            return FREE_PLANE_BASE + int(label.split()[1]) - 1
        if label == "—":
            return None
        return int(label.split()[0]) - 1

    def _label_of(self, i):
        return f"{i + 1} ({self.planes[i].orientation})" if i < FREE_PLANE_BASE else f"free {i - FREE_PLANE_BASE + 1}"

    def _refresh_data(self):
        """Redraw the collected data (points per feature) and save the session."""
        with self.lock:
            data = self.session.data(self.sd, self.planes)
            self.session.save(self.sd, self.planes)
        s = self.server.scene
        for name in list(self.n_data):
            if name not in data:
                self.n_data.pop(name).remove()
        for name, pts in data.items():
            if name in self.n_data:
                self.n_data[name].points = pts.astype(np.float32)
            else:
                size = 2.5 if name.endswith("centerline") else 0.6 if name.endswith("contour") or name == "posterior" else 1.2
                self.n_data[name] = s.add_point_cloud(f"/data/{name}", pts.astype(np.float32), FEATURE_COLOURS[name],
                                                      point_size=size, precision="float32", point_shape="circle")
        n = min(self.session.stylus_count, len(self.sd.stylus_path))
        self.stylus_md.content = f"{n} of {len(self.sd.stylus_path)} sweep points digitised"
        counts = ", ".join(f"{k} {len(v)}" for k, v in sorted(data.items())) or "none yet"
        drawn = len([c for c in self.session.contours if c.vertices])
        self.plane_md.content = (f"Planes added (auto): {[self._label_of(i) for i in self.session.planes_added] or 'none'}; "
                                 f"contours drawn: {drawn}.  \nData: {counts}")
        self.btn_warm.disabled = self.worker is None or self.worker.last is None
        self._show_drawing()

    def _show_drawing(self):
        """Vertices of the contour being drawn, as markers on the image."""
        if self.current is None or self.current_plane is None or self.current.plane != self.current_plane:
            if self.n_drawn is not None:
                self.n_drawn.visible = False
            return
        from ..simulation.probe import pixels_to_tracker

        v = np.array(self.current.vertices, float).reshape(-1, 2)
        pts = pixels_to_tracker(self.sd.probe, self.planes[self.current.plane].probe_to_tracker, v[:, 0], v[:, 1])
        self.n_drawn = self.server.scene.add_point_cloud("/drawing/vertices", pts.astype(np.float32), (255, 255, 0),
                                                         point_size=2.0, precision="float32", point_shape="diamond")

    def _visibility(self):
        self.n_liver.visible = self.cb_preop.value
        for n in self.n_vessels:
            n.visible = self.cb_vessels.value
        if self.sd is not None:
            self.n_truth.visible = self.cb_truth.value
        coloured = self.cb_error.value and "error" in self.n_reg
        for name, node in self.n_reg.items():
            # the error-coloured liver replaces the plain one while "Colour by error" is on
            shown = coloured if name == "error" else (not coloured if name == "liver" else True)
            node.visible = self.cb_registered.value and shown

    # ------------------------------------------------------------------ stylus
    def start_stylus(self):
        if self.stylus_thread is not None and self.stylus_thread.is_alive():
            self.stylus_stop.set()
            return
        self.stylus_stop.clear()
        self.stylus_thread = threading.Thread(target=self._sweep_stylus, daemon=True)
        self.stylus_thread.start()

    def _sweep_stylus(self):
        """Move the tool tip along the sweep at the chosen pace, leaving digitised points."""
        path = self.sd.stylus_path
        self.btn_stylus.label = "Stop digitising"
        self.n_tool.visible = True
        i = min(self.session.stylus_count, len(path))
        pos = path[i] if i < len(path) else path[-1]
        last_saved = time.monotonic()
        while i < len(path) and not self.stylus_stop.is_set():
            step = STYLUS_MM_PER_S * self.stylus_speed.value * FRAME_S
            while step > 0 and i < len(path):
                d = np.linalg.norm(path[i] - pos)
                if d <= step:
                    pos, step, i = path[i], step - d, i + 1
                else:
                    pos, step = pos + (path[i] - pos) * step / d, 0.0
            _, j = self.truth_tree.query(pos)
            self.n_tool.wxyz = _wxyz(_rotation_z_to(self.truth_normals[j] + np.array([0.0, 0.3, 0.3])))
            self.n_tool.position = pos
            with self.lock:
                self.session.stylus_count = i
            if time.monotonic() - last_saved > 0.5 or i == len(path):
                self._refresh_data()
                last_saved = time.monotonic()
            time.sleep(FRAME_S)
        self._refresh_data()
        self.n_tool.visible = False
        self.btn_stylus.label = "Digitise anterior surface"

    def collect_stylus_now(self):
        self.stylus_stop.set()
        if self.stylus_thread is not None:
            self.stylus_thread.join()
        with self.lock:
            self.session.stylus_count = len(self.sd.stylus_path)
        self._refresh_data()

    # ------------------------------------------------------------------ ultrasound
    def show_plane(self, index):
        if index is None or index not in self.planes:
            return
        p = self.planes[index]
        self.current_plane = index
        T = p.probe_to_tracker
        self.n_probe.wxyz, self.n_probe.position, self.n_probe.visible = _wxyz(T[:3, :3]), T[:3, 3], True
        img = p.image if p.image is not None else np.zeros((self.sd.probe.height_px, self.sd.probe.width_px), np.uint8)
        # viser draws an image's first row at the node's −y edge; flipped, row 0 sits at the probe face
        self.n_image.image = np.repeat(np.flipud(img)[..., None], 3, axis=2)
        label = self._label_of(index)
        if self.plane_dd.value != label:
            self.plane_dd.value = label
        if getattr(self, "n_gizmo", None) is not None:
            self.n_gizmo.wxyz, self.n_gizmo.position = self.n_probe.wxyz, self.n_probe.position
        self._show_drawing()

    def auto_segment(self):
        if self.current_plane is None:
            self.notify("Ultrasound", "Choose a plane first.")
            return
        with self.lock:
            if self.current_plane not in self.session.planes_added:
                self.session.planes_added.append(self.current_plane)
        self._refresh_data()

    def _free_probe(self, on):
        if not on:
            if getattr(self, "n_gizmo", None) is not None:
                self.n_gizmo.remove()
                self.n_gizmo = None
            return
        if self.current_plane is None:
            self.show_plane(min(self.planes))
        self.n_gizmo = self.server.scene.add_transform_controls("/gizmo", scale=40.0, wxyz=self.n_probe.wxyz,
                                                                position=self.n_probe.position)

        @self.n_gizmo.on_drag_end
        def _(event):
            R = vtf.SO3(np.asarray(self.n_gizmo.wxyz)).as_matrix()
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, self.n_gizmo.position
            self.place_probe(T)

    def place_probe(self, T):
        """Acquire a new plane at a hand-placed pose (kept in the session)."""
        with self.lock:
            index = FREE_PLANE_BASE + len(self.session.free_planes)
            self.planes[index] = acquire_free_plane(self.sd, index, T)
            self.session.free_planes.append({"index": index, "pose": np.asarray(T).tolist()})
        self.plane_dd.options = self._plane_labels()
        self.show_plane(index)
        self._refresh_data()

    def drawing_view(self, client=None):
        """Look at the current image face-on, top of the image up."""
        if self.current_plane is None:
            self.show_plane(min(self.planes))
        self.cb_draw.value = True
        # the image lies inside the liver: hide what would stand between it and the eye
        self.cb_preop.value = self.cb_vessels.value = self.cb_registered.value = self.cb_truth.value = False
        self._visibility()
        T = self.planes[self.current_plane].probe_to_tracker
        sp_ = self.sd.probe.spacing_mm
        centre = T[:3, 3] + T[:3, 2] * (self.sd.probe.height_px - 1) / 2 * sp_
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for c in clients:
            c.camera.fov = np.radians(DRAWING_FOV_DEG)
            c.camera.up_direction = -T[:3, 2]
            c.camera.position = centre + T[:3, 1] * DRAWING_DISTANCE_MM  # viser moves look_at with position,
            c.camera.look_at = centre  # so the target is set second

    def _image_clicked(self, event):
        if not self.cb_draw.value or self.current_plane is None:
            return
        p = self.planes[self.current_plane]
        px = click_to_pixel(self.sd.probe, p.probe_to_tracker, event.ray_origin, event.ray_direction)
        if px is None:
            return
        feature = DRAWABLE[self.draw_feature.value]
        with self.lock:
            c = self.current
            if c is None or c.plane != self.current_plane or c.feature != feature:
                c = self.current = Contour(self.current_plane, feature)
                self.session.contours.append(c)
            c.vertices.append(px)
        self._refresh_data()

    def _contour_command(self, cmd):
        with self.lock:
            c = self.current
            if cmd == "Close" and c is not None:
                if len(c.vertices) >= 3:
                    c.closed = True
                    self.current = None
                else:
                    self.notify("Contour", "A closed contour needs at least 3 vertices.")
            elif cmd == "Finish line":
                self.current = None
            elif cmd == "Undo":
                if c is None and self.session.contours:
                    c = self.current = self.session.contours[-1]
                    c.closed = False
                if c is not None:
                    if c.vertices:
                        c.vertices.pop()
                    if not c.vertices:
                        self.session.contours.remove(c)
                        self.current = None
            elif cmd == "Clear plane":
                self.session.contours = [x for x in self.session.contours if x.plane != self.current_plane]
                if self.current_plane in self.session.planes_added:
                    self.session.planes_added.remove(self.current_plane)
                self.current = None
        self._refresh_data()

    # ------------------------------------------------------------------ registration
    def _data(self, kind):
        with self.lock:
            return self.session.data(self.sd, self.planes, surface_only=kind == "surface")

    def node_positions(self, rigid, beta):
        """All mesh nodes at state β in tracker space, (M, 3) mm."""
        nodes = self.model.basis.nodes
        if beta is None:
            return rigid.apply(nodes)
        return rigid.apply(deform_points(self.model.basis, self.model.centroid, beta, nodes, B=sp.identity(len(nodes))))

    def register(self, kind):
        if self.worker is None:
            self.notify("Registration", "Still preparing the registration model.")
            return False
        data = self._data(kind)
        npts = sum(len(v) for v in data.values())
        if npts < 3:
            self.notify("Registration", "Collect data first (stylus sweep or an ultrasound plane).", error=True)
            return False
        if self.worker.busy:  # checked before touching the running job's label and trace
            self.notify("Registration", "A registration is already running; wait for it or cancel it.")
            return False
        self.run_label = {"rigid": "rigid", "surface": "deformable, surface", "all": "deformable, all data",
                          "warm": "deformable, all data (warm)"}[kind]
        self.run_trace, self.streamed = [], 0
        self.run_points = npts
        self.run_t0 = time.monotonic()
        ok = self.worker.start(data, deform=kind != "rigid", warm=kind == "warm")
        if not ok:
            self.notify("Registration", "A registration is already running; wait for it or cancel it.")
            return False
        self.btn_cancel.disabled = False
        self.reg_md.content = f"Running **{self.run_label}** on {npts} points…"
        return True

    def _on_update(self, u):
        self.streamed += 1
        s = self.server.scene
        for name, pts in (("liver", u.liver), *u.vessels.items()):
            if name in self.n_reg:
                self.n_reg[name].vertices = pts.astype(np.float32)
            elif name == "liver":
                self.n_reg[name] = s.add_mesh_simple("/registered/liver", pts.astype(np.float32),
                                                     self.model.features["liver"].cells, color=REGISTERED, opacity=0.6,
                                                     side="double")
            else:
                colour = tuple(int(c * 0.6) for c in (PORTAL if name == "portal" else HEPATIC))
                self.n_reg[name] = s.add_mesh_simple(f"/registered/{name}", pts.astype(np.float32),
                                                     self.model.features[name].cells, color=colour)
        if self.truth_nodes is not None:
            err = np.linalg.norm(self.node_positions(u.rigid, u.beta) - self.truth_nodes, axis=1).mean()
            self.run_trace.append((u.elapsed, err))
            t, e = np.array(self.run_trace).T
            if len(t) >= 2:
                self.plot.data = (t, e)
        err = f", mean error {self.run_trace[-1][1]:.2f} mm" if self.run_trace else ""
        self.reg_md.content = f"**{self.run_label}** — iteration {u.iteration}, Ω = {u.omega:.4g}, {u.elapsed:.2f} s{err}"

    def _on_done(self, reg):
        seconds = time.monotonic() - self.run_t0
        self.btn_cancel.disabled = True
        self.btn_warm.disabled = False
        entry = {"run": self.run_label, "points": self.run_points, "seconds": round(seconds, 3),
                 "iterations": reg.libr.iterations if reg.libr else 0,
                 "stop": reg.libr.stop_reason if reg.libr else "rigid", "updates_streamed": self.streamed}
        if self.truth_nodes is not None:
            beta = reg.libr.beta if reg.libr is not None else None
            x = self.node_positions(reg.rigid, beta)
            err = np.linalg.norm(x - self.truth_nodes, axis=1)
            entry.update(error_mean_mm=round(float(err.mean()), 3), error_max_mm=round(float(err.max()), 3))
            self.last_error = err
            self._colour_by_error(x, err)
        with self.lock:
            self.session.log.append(entry)
            self.session.save(self.sd, self.planes)
        self.last_reg = reg
        self._refresh_log()
        self._visibility()

    def _colour_by_error(self, x, err):
        surf = self.model.basis.surface
        vmax = max(float(err.max()), 1e-6)
        mesh = trimesh.Trimesh(x[surf], self.model.features["liver"].cells, process=False)
        mesh.visual.vertex_colors = error_colours(err[surf], vmax)
        self.n_reg["error"] = self.server.scene.add_mesh_trimesh("/registered/error", mesh)
        self.error_scale = vmax

    def _on_error(self, exc):
        self.btn_cancel.disabled = True
        msg = str(exc) if isinstance(exc, NavappError) else f"{exc.__class__.__name__}: {exc}"
        self.reg_md.content = f"**Registration failed:** {msg}"
        self.notify("Registration failed", msg, error=True)

    def _refresh_log(self):
        log = self.session.log if self.session else []
        if not log:
            self.log_md.content = ""
            return
        rows = ["| run | points | s | its | mean err | max err |", "|---|---|---|---|---|---|"]
        for e in log[-8:]:
            rows.append(f"| {e['run']} | {e['points']} | {e['seconds']:.2f} | {e['iterations']} | "
                        f"{e.get('error_mean_mm', float('nan')):.2f} | {e.get('error_max_mm', float('nan')):.2f} |")
        last = log[-1]
        head = ""
        if "error_mean_mm" in last:
            head = (f"**Last: mean error {last['error_mean_mm']:.2f} mm, max {last['error_max_mm']:.2f} mm, "
                    f"{last['seconds']:.2f} s, {last['updates_streamed']} updates streamed "
                    f"({last['updates_streamed'] / max(last['seconds'], 1e-9):.1f}/s)**\n\n")
        if "error_mean_mm" in last and self.last_error is not None:  # a restored log has no coloured model yet
            head += ("<div style='height:10px;background:linear-gradient(to right,#30123b,#4686fb,#1ae4b6,#a2fc3c,"
                     "#fabb39,#e4460a,#7a0403)'></div>\n\n"
                     f"error colour scale: 0 mm … {self.error_scale:.1f} mm\n\n")
        self.log_md.content = head + "\n".join(rows)

    # ------------------------------------------------------------------ cost panel
    def sweep(self):
        if self.truth_nodes is None:
            self.notify("Cost", "This panel needs the true deformation (simulated scenes).")
            return
        data = self._data("all")
        if sum(len(v) for v in data.values()) < 3:
            self.notify("Cost", "Collect data first.", error=True)
            return
        rows = []
        x0 = self.model.basis.nodes

        def on_row(r):
            rows.append(r)
            t = np.array([x.seconds for x in rows])
            e = np.array([x.tre_mean_mm for x in rows])
            o = np.argsort(t)
            self.cost_plot.data = (t[o], e[o])
            front = pareto_front(t, e)
            lines = ["| setting | s | TRE mm | its |", "|---|---|---|---|"]
            for j in o:
                lines.append(f"| {rows[j].label}{' ★' if front[j] else ''} | {rows[j].seconds:.2f} | "
                             f"{rows[j].tre_mean_mm:.2f} | {rows[j].iterations} |")
            self.cost_md.content = "\n".join(lines)

        B = sp.identity(len(x0), format="csr")  # the targets are the mesh nodes themselves
        ok = self.worker.submit(lambda cancel: lm_sweep(self.model, data, x0, self.truth_nodes, cancel=cancel,
                                                        on_row=on_row, B=B),
                                lambda rows_: self.notify("Cost", f"{len(rows_)} settings run."))
        if not ok:
            self.notify("Cost", "A registration is running; try again when it has finished.")

    # ------------------------------------------------------------------ export
    def export(self):
        reg = getattr(self, "last_reg", None)
        if reg is None:
            self.notify("Export", "Register first: the export holds the registered model.", error=True)
            return
        out = self.session.folder / "export"
        files = export(out, reg, self.sd, self._data("all"))
        self.notify("Export", f"{len(files)} files written to {out}")
        self.session_md.content = f"Exported to `{out}`"

    # ------------------------------------------------------------------ guided demo
    def _show_step(self):
        st = STEPS[self.step]
        self.guide_md.content = f"**Step {self.step + 1} of {len(STEPS)}: {st.title}**  \n{st.text}"
        self.guide_btn.label = st.button
        self.guide_btn.disabled = self.sd is None and self.step > 1 or self.worker is None and self.step > 2

    def _guide_nav(self, value):
        self.step = max(0, self.step - 1) if value.startswith("◀") else min(len(STEPS) - 1, self.step + 1)
        self._show_step()

    def _guide_action(self, event):
        ok = getattr(self, STEPS[self.step].action)(event.client)
        if ok is not False and self.step < len(STEPS) - 1:
            self.step += 1
        self._show_step()

    def guide_preop(self, client):
        self.cb_preop.value, self.cb_vessels.value, self.cb_truth.value = True, True, False
        self._visibility()
        self._frame_camera(client)

    def guide_truth(self, client):
        self.cb_truth.value = True
        self._visibility()

    def guide_stylus(self, client):
        self.cb_truth.value = False
        self._visibility()
        self.start_stylus()

    def guide_rigid(self, client):
        if self.stylus_thread is not None:
            self.stylus_thread.join()
        return self.register("rigid")

    def guide_surface(self, client):
        self.worker.join()
        return self.register("surface")

    def guide_plane(self, client):
        self.worker.join()
        self.show_plane(self.demo_plane())

    def demo_plane(self):
        """The first preset plane that cuts a portal vein branch across (a closed contour to draw)."""
        for i in sorted(self.planes):
            if "portal_centerline" in self.planes[i].features:
                return i
        return min(self.planes)

    def guide_draw(self, client):
        self.draw_feature.value = "PV contour"
        self.drawing_view(client)

    def guide_all(self, client):
        self.cb_draw.value = False
        self.cb_preop.value = self.cb_vessels.value = self.cb_registered.value = True
        self._visibility()
        self._contour_command("Close") if self.current is not None and len(self.current.vertices) >= 3 else None
        self._frame_camera(client)
        return self.register("warm" if self.worker.last is not None else "all")

    def guide_compare(self, client):
        self.worker.join()
        self._refresh_log()
        self.notify("Comparison", "The Registration panel lists every run with its error and time.")


def serve(scene, host="127.0.0.1", port=8080, session_dir=None, edge=4.0, k=45, cache_root=None):
    """Start the viewer and block until interrupted."""
    app = App(scene, host, port, session_dir, edge, k, cache_root)
    print(f"navapp: viewer at {app.url}  (Ctrl+C to stop)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    return app
