"""Tracked-stylus digitisation: parallel swaths across the anterior surface, as a surgeon
sweeps the stylus tip, until the requested fraction of the anterior area is covered."""

import numpy as np

SWATH_WIDTH_MM = 8.0
SPACING_MM = 3.0  # one digitised point per ~3 × 3 mm of swath


def swath_pattern(vertices, areas, anterior, coverage, rng):
    """Vertex indices (sorted by sweep order) of the swaths, their covered fraction of the
    anterior area, and the sweep direction. ``areas`` (V,) lumped vertex areas, mm²."""
    ant = np.flatnonzero(anterior)
    total = areas[ant].sum()
    angle = rng.uniform(0, np.pi)
    across = np.array([np.cos(angle), 0.0, np.sin(angle)])  # swaths run perpendicular to this
    s = vertices[ant] @ across
    order = rng.permutation(np.arange(s.min(), s.max(), SWATH_WIDTH_MM * 2.5))
    chosen = np.zeros(len(ant), bool)
    for centre in order:
        chosen |= np.abs(s - centre) < SWATH_WIDTH_MM / 2
        if areas[ant][chosen].sum() >= coverage * total:
            break
    idx = ant[chosen]
    along = np.cross(across, [0.0, 1.0, 0.0])
    idx = idx[np.lexsort((vertices[idx] @ along, np.round(vertices[idx] @ across / SWATH_WIDTH_MM)))]
    return idx, float(areas[idx].sum() / total), across


def thin(points, spacing=SPACING_MM):
    """Keep one point per ``spacing`` mm voxel (the stylus samples at a steady rate)."""
    if len(points) == 0:
        return points
    key = np.floor(points / spacing).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return points[np.sort(first)]


def surface_patch(vertices, faces, centre, coverage, anterior_area, count, rng):
    """One contiguous partial scan of the surface: ``count`` random points, uniform by area,
    on the triangles within a growing distance of ``centre`` (mm) until they cover
    ``coverage`` × ``anterior_area`` (mm²). Triangles facing posterior (n_y < −0.2) are
    left out: a scan from the front does not see through a thin lobe. Returns the faces'
    indices (T,), the points' face index (count,) and barycentric coordinates (count, 3),
    so the caller can place them on the deformed surface, and the covered area (mm²)."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(fn, axis=1)
    seen = fn[:, 1] / np.maximum(2 * area, 1e-300) > -0.2
    d = np.linalg.norm(tri.mean(1) - np.asarray(centre, float), axis=1)
    d[~seen] = np.inf
    order = np.argsort(d)
    enough = np.searchsorted(np.cumsum(area[order]), coverage * anterior_area) + 1
    chosen = order[:min(enough, int(np.isfinite(d).sum()))]
    pick = rng.choice(chosen, size=count, p=area[chosen] / area[chosen].sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    bary = np.column_stack([1 - s, s * (1 - r2), s * r2])
    return chosen, pick, bary, float(area[chosen].sum())
