"""Deterministic liver phantoms: an implicit liver, its portal and hepatic trees, labels.

A phantom is fully determined by its index (0, 1, 2, …): the index seeds every random
choice, so the same index gives the same bytes on every machine with the same numpy.
Shape recipe (mm, +x patient-left, +y anterior, +z superior):
- a large right lobe and a thin, tapering left lobe joined by a smooth union (the dome is
  the top of that union);
- a sloping inferior (visceral) cut plane, higher anteriorly, whose crease with the dome
  makes the left and right inferior ridges;
- a flattened posterior face (bare area), a hilum notch carved into the visceral surface,
  an umbilical notch at the inferior border where the falciform ligament ends;
- low-frequency bumps so that no two phantoms are alike;
- two tumours (``make_tumours``), smooth irregular ellipsoids well inside the parenchyma,
  drawn from their own random stream so that the liver and vessels are as before.
"""

import copy
import threading
from dataclasses import dataclass

import numpy as np
import trimesh
from skimage.measure import marching_cubes

from ..geometry.transforms import apply_rigid
from . import sdf
from .model import REGION_NAMES, PreopModel
from .targets import Target, from_surface
from .vessels import grow_hepatic_tree, grow_portal_tree, tube_surface


@dataclass(frozen=True)
class LiverShape:
    """Parameters of the implicit liver (mm)."""

    right_centre: tuple
    right_radii: tuple
    left_centre: tuple
    left_radii: tuple
    left_tilt_deg: float  # left lobe tips down toward its lateral end
    lobe_blend: float
    inferior_point: tuple  # a point on the visceral cut plane
    inferior_normal: tuple  # outward normal of the visceral plane (points inferior-anterior)
    posterior_y: float
    hilum_centre: tuple
    hilum_radius: float
    falciform_x: float
    bumps: tuple  # (amplitude, wavevector (3,), phase) triples

    def inferior_plane(self, p):
        return sdf.halfspace(p, np.array(self.inferior_point), np.array(self.inferior_normal))

    def lobes(self, p):
        c = np.cos(np.radians(self.left_tilt_deg))
        s = np.sin(np.radians(self.left_tilt_deg))
        rot = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])
        right = sdf.ellipsoid(p, np.array(self.right_centre), np.array(self.right_radii))
        left = sdf.ellipsoid(p, np.array(self.left_centre), np.array(self.left_radii), rot)
        d = sdf.smooth_union(right, left, self.lobe_blend)
        for amp, kvec, phase in self.bumps:
            d = d + amp * np.sin(np.asarray(p, float) @ np.array(kvec) + phase)
        return d

    def __call__(self, p):
        """Signed distance-like value (...,) mm, negative inside the liver."""
        p = np.asarray(p, float)
        d = sdf.smooth_intersection(self.lobes(p), self.inferior_plane(p), 3.0)
        d = sdf.smooth_intersection(d, self.posterior_y - p[..., 1], 12.0)
        d = sdf.smooth_subtraction(d, sdf.sphere(p, np.array(self.hilum_centre), self.hilum_radius), 6.0)
        notch = self.umbilical_notch_centre()
        d = sdf.smooth_subtraction(d, sdf.sphere(p, notch, 7.0), 3.0)
        return d

    def umbilical_notch_centre(self) -> np.ndarray:
        """Where the falciform line meets the inferior border, found along the plane."""
        x = self.falciform_x
        ys = np.linspace(-80, 120, 801)
        n = np.array(self.inferior_normal) / np.linalg.norm(self.inferior_normal)
        p0 = np.array(self.inferior_point)
        # points of the visceral plane at x = falciform_x; keep the most anterior one inside the lobes
        zs = p0[2] - (n[0] * (x - p0[0]) + n[1] * (ys - p0[1])) / n[2]
        pts = np.column_stack([np.full_like(ys, x), ys, zs])
        inside = self.lobes(pts) < 0
        return pts[np.flatnonzero(inside)[-1]] if inside.any() else pts[len(ys) // 2]


def liver_shape(index: int) -> LiverShape:
    """The implicit liver of phantom ``index``; index 0 is the default phantom."""
    rng = np.random.default_rng(20200 + index)
    j = lambda scale, n=3: rng.uniform(-scale, scale, n)  # noqa: E731
    rr = np.array([63.0, 84.0, 75.0]) * (1 + j(0.08))
    rc = np.array([-39.0, 0.0, 0.0]) + j(5.0)
    lr = np.array([69.0, 48.0, 19.0]) * (1 + j(0.10))
    lc = np.array([43.0, 18.0, 26.0]) + j(6.0)
    slope = 0.38 + rng.uniform(-0.06, 0.06)
    normal = np.array([rng.uniform(-0.05, 0.05), slope, -1.0])
    inf_pt = np.array([0.0, 0.0, -33.0 + rng.uniform(-4, 4)])
    hilum_y = -8.0 + rng.uniform(-4, 4)
    hilum_x = -8.0 + rng.uniform(-5, 5)
    n = normal / np.linalg.norm(normal)
    hz = inf_pt[2] - (n[0] * hilum_x + n[1] * (hilum_y - inf_pt[1])) / n[2]
    bumps = tuple(
        (float(rng.uniform(1.5, 3.0)), tuple(rng.normal(size=3) * 2 * np.pi / 110.0), float(rng.uniform(0, 2 * np.pi)))
        for _ in range(3)
    )
    return LiverShape(
        right_centre=tuple(rc), right_radii=tuple(rr), left_centre=tuple(lc), left_radii=tuple(lr),
        left_tilt_deg=float(12 + rng.uniform(-4, 4)), lobe_blend=18.0,
        inferior_point=tuple(inf_pt), inferior_normal=tuple(normal),
        posterior_y=float(-57.0 + rng.uniform(-4, 4)),
        hilum_centre=(hilum_x, hilum_y, float(hz)), hilum_radius=float(16 + rng.uniform(-2, 2)),
        falciform_x=float(8.0 + rng.uniform(-5, 5)), bumps=bumps,
    )


def polygonise(fn, lo, hi, spacing: float) -> trimesh.Trimesh:
    """Marching-cubes surface of {fn < 0} in the box [lo, hi] (mm), outward normals."""
    lo = np.asarray(lo, float) - 2 * spacing
    hi = np.asarray(hi, float) + 2 * spacing
    axes = [np.arange(a, b + spacing, spacing) for a, b in zip(lo, hi, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    values = fn(grid.reshape(-1, 3)).reshape(grid.shape[:3])
    values[[0, -1], :, :] = values[:, [0, -1], :] = values[:, :, [0, -1]] = 1.0
    verts, faces, _, _ = marching_cubes(values, 0.0, spacing=(spacing,) * 3)
    mesh = trimesh.Trimesh(verts + lo, faces[:, ::-1], process=True)
    mesh.fix_normals()
    return mesh


def smooth_surface(mesh: trimesh.Trimesh, iterations: int = 10) -> trimesh.Trimesh:
    """Taubin smoothing (volume-preserving) to take the staircase out of marching cubes."""
    out = mesh.copy()
    trimesh.smoothing.filter_taubin(out, lamb=0.5, nu=-0.53, iterations=iterations)
    return out


def label_regions(shape: LiverShape, mesh: trimesh.Trimesh) -> np.ndarray:
    """Per-vertex region codes (V,) into REGION_NAMES.

    - ridges: the inferior border, where the anterior face turns into the visceral face
      (normals tilted 12–53° below horizontal, or within 7 mm of the crease with the
      visceral plane), anterior of the hilum, split left/right at the falciform x;
    - falciform: a 10 mm wide band at the falciform x on the anterior/superior surface;
    - anterior: outward normal facing anterior (n_y > 0.1) and not inferior (n_z > -0.55),
      i.e. what a laparoscope and a stylus reach;
    - posterior: everything else (posterior face, visceral surface, bare area).
    """
    v = mesh.vertices
    n = mesh.vertex_normals
    codes = np.full(len(v), REGION_NAMES.index("posterior"))
    anterior = (n[:, 1] > 0.1) & (n[:, 2] > -0.55)
    codes[anterior] = REGION_NAMES.index("anterior")
    falc = (np.abs(v[:, 0] - shape.falciform_x) < 5.0) & (n[:, 1] + n[:, 2] > 0.3) & (v[:, 1] > -10)
    codes[falc] = REGION_NAMES.index("falciform")
    # the inferior border: where the anterior face turns into the visceral face (the crease
    # with the visceral plane on the right lobe, the rounded rim of the thin left lobe)
    turning = (n[:, 1] > 0.15) & (n[:, 2] < -0.2) & (n[:, 2] > -0.8)
    crease = (np.abs(shape.lobes(v)) < 7.0) & (np.abs(shape.inferior_plane(v)) < 7.0)
    ridge = (turning | crease) & (v[:, 1] > shape.hilum_centre[1] + 5)
    left = v[:, 0] > shape.falciform_x
    codes[ridge & left] = REGION_NAMES.index("ridge_left")
    codes[ridge & ~left] = REGION_NAMES.index("ridge_right")
    return codes


TUMOUR_DIAMETERS_MM = (22.0, 14.0)  # nominal; the irregular shape makes the largest diameter up to ~15 % more
TUMOUR_LIVER_CLEARANCE_MM = 8.0  # every tumour vertex at least this far inside the liver surface
TUMOUR_VESSEL_CLEARANCE_MM = 2.0  # and clear of the portal and hepatic vessel walls


def irregular_ellipsoid(centre, radii, rng, subdivisions: int = 3) -> trimesh.Trimesh:
    """A smooth lumpy ellipsoid: an icosphere (642 vertices at 3 subdivisions) scaled to
    ``radii``, its radius modulated by ±~6 % low-frequency waves, randomly rotated.
    Star-shaped about ``centre`` (hence closed and never self-intersecting)."""
    ico = trimesh.creation.icosphere(subdivisions)
    d = ico.vertices / np.linalg.norm(ico.vertices, axis=1, keepdims=True)
    r = np.ones(len(d))
    for _ in range(3):
        k = rng.normal(size=3)
        k *= rng.uniform(2.0, 3.5) / np.linalg.norm(k)
        r += rng.uniform(0.02, 0.035) * np.sin(d @ k + rng.uniform(0, 2 * np.pi))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))  # a rotation, not a reflection: the winding stays outward
    v = apply_rigid(q, np.asarray(centre, float), (d * r[:, None]) * np.asarray(radii, float))
    return trimesh.Trimesh(v.astype(np.float32).astype(float), ico.faces, process=False)


def make_tumours(shape: LiverShape, liver: trimesh.Trimesh, vessels, index: int) -> list[Target]:
    """The phantom's tumours: one of ~22 mm in the right lobe, one of ~14 mm in the left
    (or anywhere if the left lobe has no room), each centred at a random point of the
    anterior half of the places where it fits: ``TUMOUR_LIVER_CLEARANCE_MM`` inside the
    surface and clear of every vessel. Deterministic per ``index`` (own random stream)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(40400 + index)
    lo, hi = liver.bounds
    grid = np.stack(np.meshgrid(*[np.arange(a, b, 3.0) for a, b in zip(lo, hi, strict=True)], indexing="ij"), -1)
    grid = grid.reshape(-1, 3)
    grid = grid[shape(grid) < 0]
    d_liver = cKDTree(liver.vertices).query(grid)[0] - 1.5  # vertex distance overestimates by < half an edge
    d_vessel = np.full(len(grid), np.inf)
    for v in vessels:
        if v is not None:
            d_vessel = np.minimum(d_vessel, cKDTree(v.vertices).query(grid)[0])
    tumours: list[Target] = []
    for n, (diameter, side) in enumerate(zip(TUMOUR_DIAMETERS_MM, ("right", "left"), strict=True)):
        radii = diameter / 2 * (1 + rng.uniform(-0.12, 0.12, 3))
        reach = radii.max() * 1.08  # the largest radius the modulation can give
        ok = (d_liver >= reach + TUMOUR_LIVER_CLEARANCE_MM) & (d_vessel >= reach + TUMOUR_VESSEL_CLEARANCE_MM)
        for t in tumours:
            ok &= np.linalg.norm(grid - t.centre, axis=1) >= reach + t.diameter_mm / 2 + 10.0
        lobe = grid[:, 0] > shape.falciform_x if side == "left" else grid[:, 0] < shape.falciform_x
        cand = grid[ok & lobe] if (ok & lobe).any() else grid[ok]
        if len(cand) == 0:
            continue
        cand = cand[cand[:, 1] >= np.median(cand[:, 1])]  # the anterior half: within the probe's reach
        centre = cand[rng.integers(len(cand))]
        tumours.append(from_surface(f"tumour{n + 1}", irregular_ellipsoid(centre, radii, rng)))
    return tumours


_built: dict[tuple[int, float, float], PreopModel] = {}  # this process's phantoms, as built
_built_lock = threading.Lock()


def make_phantom(index: int = 0, surface_spacing: float = 2.0, vessel_spacing: float = 1.0) -> PreopModel:
    """Phantom ``index``: liver surface, PV/HV surfaces and centerlines, labels, tumours.

    Built once per process and arguments (``build_phantom``, ~3.5 CPU s; a viewer's start-up
    and a scene's simulation each asked for it); every call returns its own copy, so a caller
    that changes it changes nobody else's."""
    key = (int(index), float(surface_spacing), float(vessel_spacing))
    with _built_lock:
        model = _built.get(key)
    if model is None:
        model = build_phantom(*key)
        with _built_lock:
            model = _built.setdefault(key, model)
    return copy.deepcopy(model)


def build_phantom(index: int = 0, surface_spacing: float = 2.0, vessel_spacing: float = 1.0) -> PreopModel:
    """Build phantom ``index`` afresh (``make_phantom`` keeps what it builds)."""
    if index < 0:
        raise ValueError("phantom index must be >= 0")
    shape = liver_shape(index)
    lo, hi = np.array([-125.0, -80.0, -90.0]), np.array([125.0, 100.0, 90.0])
    liver = smooth_surface(polygonise(shape, lo, hi, surface_spacing))
    # keep the largest piece: bumps must never leave a detached island
    parts = liver.split(only_watertight=True)
    if len(parts) > 1:
        liver = max(parts, key=lambda m: m.volume)
    rng = np.random.default_rng(30300 + index)
    portal_cl = grow_portal_tree(shape, rng)
    hepatic_cl = grow_hepatic_tree(shape, rng)
    portal = tube_surface(portal_cl, vessel_spacing)
    hepatic = tube_surface(hepatic_cl, vessel_spacing)
    # PLY stores float32: snap now so that writing and reading a case folder is exact
    for mesh in (liver, portal, hepatic):
        mesh.vertices = mesh.vertices.astype(np.float32).astype(float)
    return PreopModel(
        liver=liver, portal=portal, hepatic=hepatic,
        portal_centerline=portal_cl, hepatic_centerline=hepatic_cl,
        regions=label_regions(shape, liver), name=f"phantom{index}",
        meta={"phantom": index}, targets=make_tumours(shape, liver, (portal, hepatic), index),
    )
