"""Bresenham rasterisation of segments and polylines onto an image pixel grid.

The same routine serves the simulator (contours of plane sections) and the app (lines a
user draws on an ultrasound image), so simulated and hand-drawn data are sampled alike.
"""

import numpy as np


def line(r0: int, c0: int, r1: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (rows, cols) of the digital segment from (r0, c0) to (r1, c1), both ends
    included, in order from the start; integer error arithmetic only.

    Walks the major axis one pixel at a time; the minor coordinate steps whenever the
    accumulated error 2·d_minor·i − d_major·(steps taken) reaches zero.
    """
    r0, c0, r1, c1 = (int(v) for v in (r0, c0, r1, c1))
    dr, dc = abs(r1 - r0), abs(c1 - c0)
    sr = 1 if r1 > r0 else -1
    sc = 1 if c1 > c0 else -1
    steep = dr > dc
    if steep:  # iterate over rows, with columns as the minor axis
        major, minor, s_major, s_minor, a0, b0 = dr, dc, sr, sc, r0, c0
    else:
        major, minor, s_major, s_minor, a0, b0 = dc, dr, sc, sr, c0, r0
    a = np.empty(major + 1, np.int64)
    b = np.empty(major + 1, np.int64)
    err = 2 * minor - major
    bb = b0
    for i in range(major):
        a[i] = a0 + s_major * i
        b[i] = bb
        while err >= 0:
            bb += s_minor
            err -= 2 * major
        err += 2 * minor
    a[major] = a0 + s_major * major
    b[major] = b0 + s_minor * minor
    return (a, b) if steep else (b, a)


def polyline(points_rc, closed=False) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of a polyline through integer (row, col) vertices (V, 2), without repeating
    the shared vertex of consecutive segments; ``closed`` joins the last vertex to the first."""
    pts = np.asarray(points_rc, dtype=np.int64).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if closed and len(pts) > 2:
        pts = np.vstack([pts, pts[:1]])
    rows, cols = [pts[:1, 0]], [pts[:1, 1]]
    for (r0, c0), (r1, c1) in zip(pts[:-1], pts[1:], strict=True):
        rr, cc = line(r0, c0, r1, c1)
        rows.append(rr[1:])
        cols.append(cc[1:])
    rr, cc = np.concatenate(rows), np.concatenate(cols)
    if closed and len(pts) > 2:
        rr, cc = rr[:-1], cc[:-1]
    return rr, cc
