"""Static pictures (PNG) of models and cases, drawn with matplotlib (no display needed).

Used for the committed figures in the README; the interactive viewer is ``navapp.app``.
"""

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from ..anatomy.model import REGION_NAMES, PreopModel  # noqa: E402

REGION_COLOURS = {
    "anterior": (0.85, 0.62, 0.52),
    "posterior": (0.55, 0.42, 0.40),
    "falciform": (0.95, 0.85, 0.20),
    "ridge_left": (0.20, 0.70, 0.30),
    "ridge_right": (0.20, 0.45, 0.85),
}


def _shade(mesh, base, light=(0.3, 0.8, 0.6)):
    light = np.asarray(light) / np.linalg.norm(light)
    k = 0.45 + 0.55 * np.clip(mesh.face_normals @ light, 0, 1)
    return np.clip(np.asarray(base)[..., :3] * k[:, None], 0, 1)


def add_mesh(ax, mesh, colour, alpha=1.0, face_colours=None):
    """Draw a trimesh on a 3D axis with simple Lambert shading."""
    base = np.broadcast_to(np.asarray(colour, float), (len(mesh.faces), 3)) if face_colours is None else face_colours
    rgb = _shade(mesh, base)
    coll = Poly3DCollection(mesh.vertices[mesh.faces], facecolors=np.column_stack([rgb, np.full(len(rgb), alpha)]),
                            linewidths=0)
    ax.add_collection3d(coll)


def frame(ax, points, elev=20, azim=-60):
    lo, hi = points.min(0), points.max(0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    ax.set_xlabel("x (mm, left)")
    ax.set_ylabel("y (mm, anterior)")
    ax.set_zlabel("z (mm, superior)")


def phantom_figure(model: PreopModel, path, title=None):
    """Two views: liver coloured by region label, and the vessel trees inside it."""
    fig = plt.figure(figsize=(12, 5.6), dpi=110)
    liver = model.liver
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    if model.regions is not None:
        vc = np.array([REGION_COLOURS[REGION_NAMES[c]] for c in model.regions])
        fc = vc[liver.faces].mean(1)
    else:
        fc = None
    add_mesh(ax, liver, REGION_COLOURS["anterior"], 1.0, fc)
    frame(ax, liver.vertices, elev=25, azim=70)
    ax.set_title("surface regions (anterior view)")
    handles = [plt.Rectangle((0, 0), 1, 1, color=REGION_COLOURS[n]) for n in REGION_NAMES]
    ax.legend(handles, REGION_NAMES, loc="lower left", fontsize=8)
    ax = fig.add_subplot(1, 2, 2, projection="3d")
    if model.portal is not None:
        add_mesh(ax, model.portal, (0.85, 0.15, 0.15))
    if model.hepatic is not None:
        add_mesh(ax, model.hepatic, (0.2, 0.35, 0.9))
    add_mesh(ax, liver, (0.8, 0.7, 0.6), 0.08)
    frame(ax, liver.vertices, elev=25, azim=70)
    ax.set_title("portal (red) and hepatic (blue) veins")
    fig.suptitle(title or model.name)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def case_figure(case_dir, path, title=None):
    """The simulated case like the paper's Fig. 4: the deformed liver, its vessels, the
    stylus data, and the 16 iUS image planes as outlined rectangles with their contours."""
    import json
    from pathlib import Path

    import trimesh

    case_dir = Path(case_dir)
    fig = plt.figure(figsize=(12, 6), dpi=110)
    ax = fig.add_subplot(1, 1, 1, projection="3d")
    liver = trimesh.load(case_dir / "truth/liver.ply")
    for name, colour in (("portal", (0.85, 0.15, 0.15)), ("hepatic", (0.2, 0.35, 0.9))):
        p = case_dir / "truth" / f"{name}.ply"
        if p.exists():
            add_mesh(ax, trimesh.load(p), colour, 0.5)
    add_mesh(ax, liver, (0.8, 0.7, 0.6), 0.10)
    for feat, colour, size in (("anterior", "k", 2), ("falciform", "y", 6), ("ridge_left", "g", 6), ("ridge_right", "c", 6)):
        f = case_dir / "intraop" / f"{feat}.csv"
        if f.exists():
            pts = np.loadtxt(f, delimiter=",", skiprows=1, ndmin=2)
            ax.scatter(*pts.T, s=size, c=colour, depthshade=False, label=f"stylus: {feat}")
    meta_path = case_dir / "intraop/us/planes.json"
    if meta_path.exists():
        meta = json.loads(meta_path.read_text())
        S = np.array(meta["image_to_probe"])
        w, h = meta["width_px"], meta["height_px"]
        corners = np.array([[0, 0, 0, 1], [w - 1, 0, 0, 1], [w - 1, h - 1, 0, 1], [0, h - 1, 0, 1], [0, 0, 0, 1]], float)
        for p in meta["planes"]:
            T = np.array(p["probe_to_tracker"])
            c = (T @ S @ corners.T).T[:, :3]
            ax.plot(*c.T, color="tab:purple" if p["orientation"] == "vertical" else "tab:orange", lw=0.8)
            pdir = case_dir / "intraop/us" / f"plane_{p['index']:02d}"
            for f in pdir.glob("*_contour.csv"):
                pts = np.loadtxt(f, delimiter=",", skiprows=1, ndmin=2)
                ax.scatter(*pts.T, s=1, c="r" if f.stem.startswith("portal") else "b", depthshade=False)
            f = pdir / "posterior.csv"
            if f.exists():
                pts = np.loadtxt(f, delimiter=",", skiprows=1, ndmin=2)
                ax.scatter(*pts.T, s=1, c="m", depthshade=False)
    frame(ax, liver.vertices, elev=28, azim=65)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(title or f"{case_dir.name}: deformed liver, stylus swaths, iUS planes "
                 "(purple vertical, orange lateral) and their contours")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
