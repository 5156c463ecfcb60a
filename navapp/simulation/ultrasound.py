"""Tracked iUS planes: poses on the anterior surface, features from plane sections of the
deformed anatomy (rasterised with Bresenham, mapped back through calibration and
tracking), and synthetic B-mode images."""

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from sklearn.cluster import KMeans

from ..anatomy.model import VESSELS
from ..defaults import FAR_WALL_COS, FAR_WALL_MIN_DEPTH_MM, N_PLANES
from ..geometry.bresenham import line
from ..geometry.planes import plane_section
from ..geometry.transforms import probe_pose
from . import effects as fx
from .probe import pixels_to_tracker, tracker_to_pixels


@dataclass
class PlaneData:
    index: int
    orientation: str  # "vertical" or "lateral"
    probe_to_tracker: np.ndarray  # true pose (4×4)
    features: dict  # feature name → (N, 3) mm, tracker space
    image: np.ndarray | None = None  # (H, W) uint8 B-mode


def plane_poses(liver_vertices, liver_normals, anterior_mask, count=N_PLANES, seed=0):
    """``count`` probe poses (half vertical, half lateral) on the deformed anterior surface,
    pointing into the liver: contacts are k-means centres of the anterior vertices."""
    half = count // 2 + count % 2
    ant = np.flatnonzero(anterior_mask)
    km = KMeans(n_clusters=half, n_init=4, random_state=seed).fit(liver_vertices[ant])
    order = np.argsort(km.cluster_centers_[:, 0])
    poses = []
    for orientation, lateral in (("vertical", np.array([0.0, 0.0, 1.0])), ("lateral", np.array([1.0, 0.0, 0.0]))):
        for c in km.cluster_centers_[order]:
            i = ant[np.argmin(np.linalg.norm(liver_vertices[ant] - c, axis=1))]
            depth = -liver_normals[i]
            poses.append((orientation, probe_pose(liver_vertices[i], lateral, depth)))
    return poses[:count]


def _components(seg_px):
    """Connected components of segments sharing end points: labels (S,), closed flags."""
    ends = np.round(seg_px.reshape(-1, 2), 6)
    _, key = np.unique(ends, axis=0, return_inverse=True)
    key = key.ravel()
    a, b = key[0::2], key[1::2]
    n = key.max() + 1
    g = coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    ncomp, lab = connected_components(g, directed=False)
    seg_lab = lab[a]
    degree = np.bincount(key, minlength=n)
    closed = np.array([np.all(degree[lab == c] == 2) for c in range(ncomp)])
    return seg_lab, closed


def _rasterise(seg_px, probe):
    """Bresenham pixels (cols, rows) of segments given in continuous pixel coordinates,
    keeping those inside the image."""
    cols, rows = [], []
    for (u0, v0), (u1, v1) in np.rint(seg_px).astype(np.int64):
        rr, cc = line(v0, u0, v1, u1)
        rows.append(rr)
        cols.append(cc)
    if not cols:
        return np.zeros(0, int), np.zeros(0, int)
    px = np.unique(np.column_stack([np.concatenate(cols), np.concatenate(rows)]), axis=0)
    ok = (px[:, 0] >= 0) & (px[:, 0] < probe.width_px) & (px[:, 1] >= 0) & (px[:, 1] < probe.height_px)
    return px[ok, 0], px[ok, 1]


def _to_px(probe, T, seg):
    c, r, _ = tracker_to_pixels(probe, T, seg.reshape(-1, 3))
    return np.column_stack([c, r]).reshape(-1, 2, 2)


def acquire_plane(index, orientation, T, probe, liver, portal, hepatic, scene_effects, rng, ledger, want_image):
    """Features (and optionally the B-mode image) of one plane of the deformed anatomy.

    liver, portal, hepatic: deformed trimesh surfaces (tracker space). Effects that apply
    to planes run here only when declared: probe compression (anatomy indented before
    sectioning), contour jitter (pixels), calibration error (pose used to map pixels
    back), tracking noise and dropout (3D points).
    """
    ledger.mark("ius_section")
    eff = {e.kind: e.params for e in scene_effects}
    origin, depth_axis, normal = T[:3, 3], T[:3, 2], T[:3, 1]
    meshes = {"liver": liver, "portal": portal, "hepatic": hepatic}
    if "probe_compression" in eff:
        p = eff["probe_compression"]
        meshes = {k: (None if m is None else _indent(m, origin, depth_axis, ledger, p)) for k, m in meshes.items()}
    measured = T
    if "calibration_error" in eff:
        measured = fx.calibration_error(T, rng, ledger, **eff["calibration_error"])
    feats = {}
    sections = {}
    for name in (*VESSELS, "liver"):
        m = meshes[name]
        if m is None:
            continue
        seg, faces = plane_section(m.vertices, m.faces, origin, normal, return_faces=True)
        if name == "liver":  # the posterior wall: faces turned away from the probe
            keep = m.face_normals[faces] @ depth_axis > FAR_WALL_COS
            far = np.einsum("sij,j->si", seg - origin, depth_axis).min(1) > FAR_WALL_MIN_DEPTH_MM
            sections["liver_all"] = _to_px(probe, T, seg)
            seg = seg[keep & far]
        sections[name] = _to_px(probe, T, seg)
    for name, feat in (("portal", "portal_contour"), ("hepatic", "hepatic_contour"), ("liver", "posterior")):
        if name not in sections or len(sections[name]) == 0:
            continue
        seg_px = sections[name]
        if "contour_jitter" in eff:
            c, r = fx.contour_jitter(seg_px[..., 0].ravel(), seg_px[..., 1].ravel(), rng, ledger,
                                     **eff["contour_jitter"])
            seg_px = np.stack([c, r], -1).reshape(seg_px.shape)
        cols, rows = _rasterise(seg_px, probe)
        if len(cols):
            feats[feat] = pixels_to_tracker(probe, measured, cols, rows)
        if name in VESSELS:
            lab, closed = _components(sections[name])
            cents = []
            for c in np.flatnonzero(closed):
                piece = seg_px[lab == c]
                cc, rr = _rasterise(piece, probe)
                inside = (np.all(piece.reshape(-1, 2) >= 0) and np.all(piece[..., 0] < probe.width_px)
                          and np.all(piece[..., 1] < probe.height_px))
                if len(cc) >= 6 and inside:
                    cents.append(pixels_to_tracker(probe, measured, [cc.mean()], [rr.mean()])[0])
            if cents:
                feats[f"{name}_centerline"] = np.array(cents)
    for k in list(feats):
        if "tracking_noise" in eff:
            feats[k] = fx.tracking_noise(feats[k], rng, ledger, **eff["tracking_noise"])
        if "dropout" in eff:
            feats[k] = fx.dropout(feats[k], rng, ledger, **eff["dropout"])
            if len(feats[k]) == 0:
                del feats[k]
    image = bmode_image(probe, sections, rng, ledger) if want_image else None
    return PlaneData(index, orientation, T, feats, image)


def _indent(mesh, origin, depth_axis, ledger, params):
    import trimesh

    v = fx.probe_compression(mesh.vertices, origin, depth_axis, ledger, **params)
    return trimesh.Trimesh(v, mesh.faces, process=False)


def _inside(seg_px, probe):
    """(H, W) bool: even–odd rule along each image column against the section segments."""
    H, W = probe.height_px, probe.width_px
    inside = np.zeros((H, W), bool)
    if len(seg_px) == 0:
        return inside
    u0, v0 = seg_px[:, 0, 0], seg_px[:, 0, 1]
    u1, v1 = seg_px[:, 1, 0], seg_px[:, 1, 1]
    rows = np.arange(H)
    for u in range(W):
        x = u + 0.5
        span = (np.minimum(u0, u1) <= x) & (np.maximum(u0, u1) > x)
        if not span.any():
            continue
        t = (x - u0[span]) / (u1[span] - u0[span])
        cross = np.sort(v0[span] + t * (v1[span] - v0[span]))
        inside[:, u] = (np.searchsorted(cross, rows + 0.5) % 2) == 1
    return inside


def bmode_image(probe, sections, rng, ledger) -> np.ndarray:
    """Synthetic B-mode: Rayleigh speckle on parenchyma, dark vessel lumens, a bright
    posterior liver boundary, and exponential depth attenuation. (H, W) uint8."""
    ledger.mark("bmode_image")
    H, W = probe.height_px, probe.width_px
    echo = np.where(_inside(sections.get("liver_all", np.zeros((0, 2, 2))), probe), 0.55, 0.12)
    for v in VESSELS:
        if v in sections:
            echo[_inside(sections[v], probe)] = 0.04
    img = echo * rng.rayleigh(scale=0.8, size=(H, W))
    if "liver" in sections and len(sections["liver"]):
        cols, rows = _rasterise(sections["liver"], probe)
        for dr in (-1, 0, 1, 2):
            r = np.clip(rows + dr, 0, H - 1)
            img[r, cols] = 1.6
    depth_mm = np.arange(H)[:, None] * probe.spacing_mm
    img *= np.exp(-depth_mm / 90.0)
    return np.clip(img * 160, 0, 255).astype(np.uint8)
