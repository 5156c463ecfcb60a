"""A tracked laparoscope's sparse depth points: the liver surface the camera sees.

The camera looks at the anterior liver from ``distance_mm`` along the anterior face's mean
outward normal, tilted ``tilt_deg`` toward inferior (a caudal port, the usual one for the
liver). A square grid of ``rays`` × ``rays`` rays spans its field of view; a random
``keep`` fraction of them return a depth (a stereo or structured-light matcher finds a
depth at a sparse set of pixels). A ray returns the first surface it hits (the liver
hides itself: a lobe in front hides what is behind), within ``far_mm``, and only where it
meets the surface at ``max_incidence_deg`` or less (grazing surfaces give no match). An
instrument in view, a capped cylinder of ``instrument_radius_mm`` from a port beside the
camera to a tip 10 mm above the surface point seen at ``instrument_at`` (image
coordinates in [-1, 1]), hides what is behind it.

Depth noise (mm) grows with depth z along the optical axis, as for stereo triangulation,
whose depth error grows with z² at a fixed baseline and focal length:

    sd(z) = sd_mm + sd_growth_mm · (z / 100 mm)²

drawn along each ray.

The camera is a tracked tool: its depth points are placed by the pose the tracker reports,
so the tracker's error is one rigid error of the camera's pose per view, shared by all the
view's points — not a separate error on each point, as on the stylus's tip, which the
tracker reports once per point. With the scene's ``tracking_noise`` declared, each of the
camera's ``MARKERS`` markers (a ring of ``marker_radius_mm`` about the shaft, ``marker_offset_mm``
behind the camera centre along it: a rigid body on the camera head) is measured with that
sd (mm, isotropic), and the tracker fits the body's definition to them (Kabsch): the fit's
rotation and shift is the pose's error, applied to every point of the view. To first order
the rotation's sd about the two axes across the shaft is sd / (r √(n/2)) rad and about the
shaft sd / (r √n), the shift at the markers' centre sd / √n per axis, so the lever arm
grows the error toward the camera and beyond it, to the liver (at sd 0.3 mm and the
defaults: 0.30° across the shaft, 1.6 mm per axis at the camera centre). The report states
the view's drawn error (``tracking``: rotation, shift of the camera centre) and the pose the
tracker reported (``tool_to_tracker``: CameraToTracker, 4 × 4 mm; the camera frame x right,
y down, z along the optical axis), which ``navapp replay`` sends with the points in the camera
frame when the tracking config makes the laparoscope a tracked tool. A ``dropout`` drops a
random fraction of the points (lost matches).

In a scene (every key optional; these are the defaults)::

    [laparoscope]
    distance_mm = 120.0          # camera from the anterior face's centre
    tilt_deg = 30.0              # toward inferior
    fov_deg = 70.0
    rays = 32                    # a 32 × 32 grid of rays
    keep = 0.5                   # of which this fraction return a depth
    far_mm = 250.0
    max_incidence_deg = 80.0
    sd_mm = 0.2
    sd_growth_mm = 0.8
    instrument_radius_mm = 0.0   # > 0: an instrument in view
    instrument_at = [0.3, 0.0]
    marker_offset_mm = 300.0     # the tracked markers' ring, behind the camera centre
    marker_radius_mm = 40.0      # its radius

First hits are found by projecting every triangle into the image and testing it, by
Möller–Trumbore, only against the rays whose pixel lies in its projected bounding box (a
z-buffer over rays, not over pixels): the whole grid costs one pass over the triangles.
"""

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ...errors import InputError
from ...features import STYLUS
from ...geometry.transforms import apply, homogeneous, kabsch
from ..effects import Ledger, dropout
from . import Acquired, Sight, SimulatedSource

NAME = "laparoscope"
FEATURE = "laparoscope"
TIP_GAP_MM = 10.0  # the instrument's tip hovers this far above the surface it points at
PORT_SIDE_MM = 60.0  # its port is this far beside the camera, on the side of its tip in the image
MARKERS = 4  # on the camera's tracked rigid body, evenly round the ring


@dataclass(frozen=True)
class LaparoscopeSpec:
    """A scene's ``[laparoscope]`` (see the module's text for each key)."""

    distance_mm: float = 120.0
    tilt_deg: float = 30.0
    fov_deg: float = 70.0
    rays: int = 32
    keep: float = 0.5
    far_mm: float = 250.0
    max_incidence_deg: float = 80.0
    sd_mm: float = 0.2
    sd_growth_mm: float = 0.8
    instrument_radius_mm: float = 0.0
    instrument_at: tuple[float, float] = (0.3, 0.0)
    marker_offset_mm: float = 300.0
    marker_radius_mm: float = 40.0


_KEYS: dict[str, type] = {"distance_mm": float, "tilt_deg": float, "fov_deg": float, "rays": int, "keep": float,
                          "far_mm": float, "max_incidence_deg": float, "sd_mm": float, "sd_growth_mm": float,
                          "instrument_radius_mm": float, "instrument_at": list, "marker_offset_mm": float,
                          "marker_radius_mm": float}
_RANGES: dict[str, tuple[float, float, str]] = {  # lo, hi, the words of the range
    "distance_mm": (10.0, 400.0, "between 10 and 400"), "tilt_deg": (0.0, 80.0, "between 0 and 80"),
    "fov_deg": (10.0, 120.0, "between 10 and 120"), "rays": (2, 512, "between 2 and 512"),
    "keep": (1e-9, 1.0, "in (0, 1]"), "far_mm": (1.0, 2000.0, "between 1 and 2000"),
    "max_incidence_deg": (1.0, 90.0, "between 1 and 90"), "sd_mm": (0.0, 20.0, "between 0 and 20"),
    "sd_growth_mm": (0.0, 20.0, "between 0 and 20"), "instrument_radius_mm": (0.0, 30.0, "between 0 and 30"),
    "marker_offset_mm": (0.0, 1000.0, "between 0 and 1000"), "marker_radius_mm": (5.0, 200.0, "between 5 and 200"),
}


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: centre (3,) mm and its right, up and forward unit axes (3,) each;
    ``half`` the tangent of half the field of view."""

    centre: np.ndarray
    right: np.ndarray
    up: np.ndarray
    forward: np.ndarray
    half: float

    def grid(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates (n,) of the pixel centres along one side (in [-half, half]),
        and the unit ray directions (n·n, 3), row by row (v outer, u inner)."""
        s = (np.arange(n) + 0.5) / n * 2 * self.half - self.half
        u, v = np.meshgrid(s, s)
        d = self.forward + u.reshape(-1, 1) * self.right + v.reshape(-1, 1) * self.up
        return s, d / np.linalg.norm(d, axis=1, keepdims=True)

    def pose(self) -> np.ndarray:
        """CameraToTracker (4, 4): the camera frame's x right, y down (image rows), z forward
        (right-handed), at the centre."""
        return homogeneous(np.column_stack([self.right, -self.up, self.forward]), self.centre)

    def ray(self, u: float, v: float) -> np.ndarray:
        """The unit direction of image coordinates (u, v) in [-1, 1] (scaled by ``half``)."""
        d = self.forward + self.half * (u * self.right + v * self.up)
        return d / np.linalg.norm(d)


def look_at(centre, target, up_hint=(0.0, 0.0, 1.0), fov_deg: float = 70.0) -> Camera:
    """A camera at ``centre`` looking at ``target`` with image-up as near ``up_hint`` as can be."""
    c = np.asarray(centre, float)
    f = np.asarray(target, float) - c
    f /= np.linalg.norm(f)
    hint = np.asarray(up_hint, float)
    if abs(hint @ f) > 0.99 * np.linalg.norm(hint):
        hint = np.array([1.0, 0.0, 0.0]) if abs(f[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    r = np.cross(f, hint)
    r /= np.linalg.norm(r)
    return Camera(c, r, np.cross(r, f), f, float(np.tan(np.radians(fov_deg) / 2)))


def first_hits(camera: Camera, n: int, vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """First hit of each ray of the camera's n × n grid on the triangle surface: distance
    along the ray (n·n,) mm, inf where it hits nothing, and the triangle hit (−1 for none).
    Triangles are binned by their projected bounding box; one with a vertex at or behind
    the camera's plane is tested against every ray."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    s, d = camera.grid(n)
    q = v - camera.centre
    z = q @ camera.forward
    ahead = z > 1e-9
    x = np.where(ahead, (q @ camera.right) / np.where(ahead, z, 1.0), 0.0)
    y = np.where(ahead, (q @ camera.up) / np.where(ahead, z, 1.0), 0.0)
    step = s[1] - s[0] if n > 1 else 2 * camera.half
    whole = ~ahead[f].all(1)  # straddles the camera's plane: its projection is unbounded
    beyond = (z[f] <= 1e-9).all(1)  # wholly behind: never hit by a forward ray
    keep = ~beyond
    # pixel index ranges of each triangle's projected box (the pixel centres within it)
    i0 = np.clip(np.ceil((x[f].min(1) - s[0]) / step), 0, n).astype(np.int64)
    i1 = np.clip(np.floor((x[f].max(1) - s[0]) / step), -1, n - 1).astype(np.int64)
    j0 = np.clip(np.ceil((y[f].min(1) - s[0]) / step), 0, n).astype(np.int64)
    j1 = np.clip(np.floor((y[f].max(1) - s[0]) / step), -1, n - 1).astype(np.int64)
    i0[whole], j0[whole], i1[whole], j1[whole] = 0, 0, n - 1, n - 1
    # a pixel centre on the box's edge may be hit through the triangle's edge: widen by one
    i0, j0 = np.maximum(i0 - 1, 0), np.maximum(j0 - 1, 0)
    i1, j1 = np.minimum(i1 + 1, n - 1), np.minimum(j1 + 1, n - 1)
    wi, wj = np.maximum(i1 - i0 + 1, 0), np.maximum(j1 - j0 + 1, 0)
    count = np.where(keep, wi * wj, 0)
    tri = np.repeat(np.arange(len(f)), count)
    k = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    wi_t = wi[tri]
    ray = (j0[tri] + k // np.maximum(wi_t, 1)) * n + (i0[tri] + k % np.maximum(wi_t, 1))
    t = _moller_trumbore(camera.centre, d[ray], v[f[tri, 0]], v[f[tri, 1]], v[f[tri, 2]])
    hit = np.isfinite(t)
    best = np.full(n * n, np.inf)
    np.minimum.at(best, ray[hit], t[hit])
    which = np.full(n * n, -1)
    first = hit & (t == best[ray])
    which[ray[first]] = tri[first]
    return best, which


def _moller_trumbore(origin, d, a, b, c, eps=1e-12) -> np.ndarray:
    """Distance along each ray (P,) to its triangle (a, b, c each (P, 3)), inf for a miss;
    both faces count (the camera may see a thin lobe's far side through nothing)."""
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > eps
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - a
    u = np.einsum("ij,ij->i", s, p) * inv
    qv = np.cross(s, e1)
    w = np.einsum("ij,ij->i", d, qv) * inv
    t = np.einsum("ij,ij->i", e2, qv) * inv
    tol = 1e-10
    inside = ok & (u >= -tol) & (w >= -tol) & (u + w <= 1 + tol) & (t > 1e-9)
    return np.where(inside, t, np.inf)


def cylinder_entry(origin, d, tip, port, radius) -> np.ndarray:
    """Distance along each ray (P,) from ``origin`` (3,) with unit directions ``d`` (P, 3)
    to where it enters the capped cylinder of ``radius`` mm between ``tip`` and ``port``
    (3,) each, inf where it misses it. 0 for a ray starting inside it."""
    a = np.asarray(port, float) - np.asarray(tip, float)
    length = float(np.linalg.norm(a))
    a /= length
    w = np.asarray(origin, float) - np.asarray(tip, float)
    da, wa = d @ a, float(w @ a)
    dp = d - da[:, None] * a
    wp = w - wa * a
    A = np.einsum("ij,ij->i", dp, dp)
    B = 2 * dp @ wp
    C = float(wp @ wp) - radius ** 2
    out = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = B ** 2 - 4 * A * C
        root = np.sqrt(np.maximum(disc, 0.0))
        parallel = A < 1e-15  # along the axis: inside the infinite cylinder for all s, or never
        s1 = np.where(parallel, np.where(C <= 0, -np.inf, np.inf), (-B - root) / (2 * A))
        s2 = np.where(parallel, np.where(C <= 0, np.inf, -np.inf), (-B + root) / (2 * A))
        miss = ~parallel & (disc < 0)
        flat = np.abs(da) < 1e-15  # across the axis: inside the slab for all s, or never
        lo = np.where(flat, np.where((0 <= wa) & (wa <= length), -np.inf, np.inf),
                      np.minimum(-wa / da, (length - wa) / da))
        hi = np.where(flat, np.where((0 <= wa) & (wa <= length), np.inf, -np.inf),
                      np.maximum(-wa / da, (length - wa) / da))
    enter, leave = np.maximum(s1, lo), np.minimum(s2, hi)
    hit = ~miss & (enter <= leave) & (leave > 0)
    out[hit] = np.maximum(enter[hit], 0.0)
    return out


def depth_sd(z, spec: LaparoscopeSpec) -> np.ndarray:
    """The depth noise's standard deviation (mm) at depth ``z`` mm: sd + growth · (z/100)²."""
    return spec.sd_mm + spec.sd_growth_mm * (np.asarray(z, float) / 100.0) ** 2


def camera_for(spec: LaparoscopeSpec, sight: Sight) -> Camera:
    """The scene's camera: ``distance_mm`` off the anterior face's centre along its mean
    outward normal, tilted ``tilt_deg`` toward inferior, looking at that centre."""
    liver = sight.liver
    face = np.any([sight.preop.region_mask(n) for n in STYLUS], axis=0)
    if not face.any():
        raise InputError("the laparoscope looks at the anterior liver surface: the anatomy has none labelled")
    target = liver.vertices[face].mean(0)
    normal = liver.vertex_normals[face].mean(0)
    normal /= np.linalg.norm(normal)
    down = np.array([0.0, 0.0, -1.0])
    inferior = down - (down @ normal) * normal  # inferior's part across the normal
    if np.linalg.norm(inferior) < 1e-6:
        inferior = np.cross(normal, [1.0, 0.0, 0.0])
    inferior /= np.linalg.norm(inferior)
    t = np.radians(spec.tilt_deg)
    back = np.cos(t) * normal + np.sin(t) * inferior
    return look_at(target + spec.distance_mm * back, target, (0.0, 0.0, 1.0), spec.fov_deg)


def instrument(camera: Camera, spec: LaparoscopeSpec, hit_at) -> tuple[np.ndarray, np.ndarray]:
    """The instrument's tip and port (3,) mm; ``hit_at`` maps a unit ray to its first-hit
    distance (inf: none)."""
    u, v = spec.instrument_at
    d = camera.ray(u, v)
    t = float(hit_at(d))
    if not np.isfinite(t):
        raise InputError(f"laparoscope.instrument_at = {list(spec.instrument_at)} sees no liver: "
                         "the instrument's tip has nothing to point at")
    tip = camera.centre + (t - TIP_GAP_MM) * d
    port = camera.centre + PORT_SIDE_MM * (camera.right if u >= 0 else -camera.right)
    return tip, port


def acquire(spec: LaparoscopeSpec, sight: Sight, rng: np.random.Generator) -> Acquired:
    """The laparoscope's depth points on the deformed liver (``Acquired``; feature
    ``laparoscope``), from the scene's camera (``camera_for``), placed by its tracked pose
    (``tracked``) and thinned by the scene's dropout."""
    sight.ledger.mark(NAME)
    cam = camera_for(spec, sight)
    got = sense(cam, spec, sight.liver, rng, sight.ledger)
    eff = {e.kind: e.params for e in sight.effects}
    pts = got.points[FEATURE]
    error = np.eye(4)
    if "tracking_noise" in eff:
        error = tracked(cam, spec, eff["tracking_noise"]["sd_mm"], rng, sight.ledger)
        pts = apply(error, pts)
        shift = apply(error, cam.centre[None])[0] - cam.centre
        angle = np.degrees(Rotation.from_matrix(error[:3, :3]).magnitude())
        got.report["tracking"] = {"rotation_deg": round(float(angle), 3),
                                  "camera_shift_mm": np.round(shift, 3).tolist()}
    if "dropout" in eff and len(pts):
        pts = dropout(pts, rng, sight.ledger, **eff["dropout"])
    got.points[FEATURE] = pts
    got.report["kept"] = {FEATURE: int(len(pts))}
    got.report["tool_to_tracker"] = (error @ cam.pose()).tolist()  # as reported: the points lie where it puts them
    return got


def markers(cam: Camera, spec: LaparoscopeSpec) -> np.ndarray:
    """The camera's tracked markers (``MARKERS``, 3) mm: a ring of ``marker_radius_mm`` about
    the shaft (the optical axis, backward), ``marker_offset_mm`` behind the camera centre."""
    a = 2 * np.pi * np.arange(MARKERS) / MARKERS
    ring = np.cos(a)[:, None] * cam.right + np.sin(a)[:, None] * cam.up
    return cam.centre - spec.marker_offset_mm * cam.forward + spec.marker_radius_mm * ring


def tracked(cam: Camera, spec: LaparoscopeSpec, sd_mm: float, rng: np.random.Generator,
            ledger: Ledger | None = None) -> np.ndarray:
    """The tracker's error of the camera's pose for one view, (4, 4) rigid, mm: the true pose
    ↦ the reported one, so a point placed by the reported pose is ``apply(error, p)``.

    Each marker (``markers``) is measured with isotropic Gaussian noise of ``sd_mm``, and the
    body's definition is fitted to the measurements (Kabsch, as a tracker fits a tool): the
    fit's rotation and shift. Draws ``MARKERS`` × 3 normals from ``rng``."""
    if ledger is not None:
        ledger.mark("tracking_noise")
    true = markers(cam, spec)
    R, t = kabsch(true, true + rng.normal(scale=sd_mm, size=true.shape))
    return homogeneous(R, t)


def sense(cam: Camera, spec: LaparoscopeSpec, surface, rng: np.random.Generator, ledger=None) -> Acquired:
    """Depth points of ``cam`` on ``surface`` (a trimesh, mm): first hits within ``far_mm``
    and ``max_incidence_deg``, less what the instrument hides, a random ``keep`` fraction of
    the rays, each moved along its ray by the depth noise ``depth_sd``."""
    V, F = np.asarray(surface.vertices, float), np.asarray(surface.faces)
    t, tri = first_hits(cam, spec.rays, V, F)
    _, d = cam.grid(spec.rays)
    report: dict = {"camera_mm": np.round(cam.centre, 2).tolist(), "forward": np.round(cam.forward, 4).tolist(),
                    "rays": int(len(d))}
    seen = np.isfinite(t) & (t <= spec.far_mm)
    if spec.instrument_radius_mm > 0:
        if ledger is not None:
            ledger.mark("laparoscope_instrument")
        tip, port = instrument(cam, spec, lambda ray: first_hit_along(cam.centre, ray, V, F))
        hidden = cylinder_entry(cam.centre, d, tip, port, spec.instrument_radius_mm) < t
        report["instrument"] = {"tip_mm": np.round(tip, 2).tolist(), "port_mm": np.round(port, 2).tolist(),
                                "hidden_rays": int((hidden & seen).sum())}
        seen &= ~hidden
    n = surface.face_normals[np.maximum(tri, 0)]
    incidence = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", n, d)), 0.0, 1.0)))
    seen &= incidence <= spec.max_incidence_deg
    idx = np.flatnonzero(seen & (rng.random(len(d)) < spec.keep))
    cos = d[idx] @ cam.forward
    z = t[idx] * cos  # depth along the optical axis
    noisy = z + rng.normal(size=len(idx)) * depth_sd(z, spec)
    pts = cam.centre + d[idx] * (noisy / cos)[:, None]
    report["points"] = int(len(pts))
    if len(z):
        report["depth_mm"] = {"min": round(float(z.min()), 1), "max": round(float(z.max()), 1)}
    return Acquired({FEATURE: pts}, report)


def first_hit_along(origin, d, vertices, faces) -> float:
    """First-hit distance of one ray (brute force over every triangle; inf for none)."""
    V, F = np.asarray(vertices, float), np.asarray(faces)
    t = _moller_trumbore(np.asarray(origin, float), np.broadcast_to(d, (len(F), 3)), V[F[:, 0]], V[F[:, 1]],
                         V[F[:, 2]])
    return float(t.min()) if len(t) else float("inf")


def parse(table, path) -> LaparoscopeSpec:
    """A scene's ``[laparoscope]`` table; one ``InputError`` line for anything wrong."""
    if not isinstance(table, dict):
        raise InputError("[laparoscope] must be a table", path)
    values: dict = {}
    for key, value in table.items():
        kind = _KEYS.get(key)
        if kind is None:
            raise InputError(f"unknown key laparoscope.{key} (known: {', '.join(_KEYS)})", path)
        if kind is list:
            if not (isinstance(value, list) and len(value) == 2 and all(
                    isinstance(c, (int, float)) and not isinstance(c, bool) and -1.0 <= c <= 1.0 for c in value)):
                raise InputError(f"laparoscope.instrument_at must be two image coordinates [u, v] in [-1, 1], "
                                 f"got {value!r}", path)
            values[key] = (float(value[0]), float(value[1]))
            continue
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not number or (kind is int and not isinstance(value, int)):
            raise InputError(f"laparoscope.{key} must be a{'n int' if kind is int else ' float'}, got {value!r}",
                             path)
        lo, hi, words = _RANGES[key]
        if not np.isfinite(value) or not lo <= value <= hi:
            raise InputError(f"laparoscope.{key} = {value!r} is out of range: must be {words}", path)
        values[key] = kind(value)
    return LaparoscopeSpec(**values)


SOURCE = SimulatedSource(NAME, always=False, parse=parse, acquire=acquire, acquires_effects=True)
