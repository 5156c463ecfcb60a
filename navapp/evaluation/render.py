"""Static pictures (PNG) of models and cases, drawn with matplotlib (no display needed).

Used for the committed figures in the README; the interactive viewer is ``navapp.app``.
"""

import numpy as np
from matplotlib.figure import Figure  # no pyplot: no global backend or figure state
from matplotlib.patches import Rectangle
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from ..anatomy.model import REGION_NAMES, PreopModel

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
    fig = Figure(figsize=(12, 5.6), dpi=110)
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
    handles = [Rectangle((0, 0), 1, 1, color=REGION_COLOURS[n]) for n in REGION_NAMES]
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
