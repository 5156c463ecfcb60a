"""Tracked linear ultrasound probe: calibration (image → probe) and tracking (probe →
tracker) transforms, as 4×4 homogeneous matrices in mm.

Image pixel (col u, row v) sits at probe coordinates (x, y, z) = ((u − u0)·s, 0, v·s):
x lateral across the array, y the elevation direction (the plane's normal), z depth into
tissue; s is the pixel spacing (mm/pixel), so ImageToProbe carries a scaling, as in PLUS.
"""

from dataclasses import dataclass

import numpy as np

from ..defaults import PROBE_HEIGHT_PX, PROBE_SPACING_MM, PROBE_WIDTH_PX
from ..geometry.transforms import homogeneous, inverse


@dataclass(frozen=True)
class Probe:
    width_px: int = PROBE_WIDTH_PX
    height_px: int = PROBE_HEIGHT_PX
    spacing_mm: float = PROBE_SPACING_MM

    def image_to_probe(self) -> np.ndarray:
        s = self.spacing_mm
        # column → lateral, row → depth; the slice column is the identity's (pixels have k = 0)
        axes = np.array([[s, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, s, 1.0]])
        return homogeneous(axes, [-s * (self.width_px - 1) / 2.0, 0.0, 0.0])


def pixels_to_tracker(probe: Probe, probe_to_tracker, cols, rows) -> np.ndarray:
    """3D tracker positions (N, 3) mm of image pixels (cols u, rows v)."""
    uv = np.column_stack([cols, rows, np.zeros(len(cols)), np.ones(len(cols))]).astype(float)
    # image coordinates are (u, v, 0, 1); ImageToProbe maps v via its second column. In homogeneous
    # coordinates, not ``transforms.apply``: for one pixel (a contour's centre, stored as a plane's
    # centerline point) NumPy's matrix–vector product rounds otherwise, 7 times in 10
    return (probe_to_tracker @ probe.image_to_probe() @ uv.T).T[:, :3]


def tracker_to_pixels(probe: Probe, probe_to_tracker, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Continuous pixel coordinates (cols, rows) of points projected onto the image
    plane, and their out-of-plane distance (mm)."""
    p = np.column_stack([np.asarray(points, float), np.ones(len(points))])
    local = (inverse(probe_to_tracker) @ p.T).T  # as ``pixels_to_tracker``, for the same bits
    s = probe.spacing_mm
    cols = local[:, 0] / s + (probe.width_px - 1) / 2.0
    rows = local[:, 2] / s
    return cols, rows, local[:, 1]


def ray_to_pixel(probe: Probe, probe_to_tracker, origin, direction):
    """Where a viewing ray (e.g. a mouse click) meets the image plane: (col, row) or None
    when the ray is parallel to the plane or the hit lies behind the ray's origin."""
    n = probe_to_tracker[:3, 1]
    o = probe_to_tracker[:3, 3]
    denom = float(np.dot(direction, n))
    if abs(denom) < 1e-12:
        return None
    t = float(np.dot(o - origin, n)) / denom
    if t < 0:
        return None
    cols, rows, _ = tracker_to_pixels(probe, probe_to_tracker, (np.asarray(origin) + t * np.asarray(direction))[None])
    return float(cols[0]), float(rows[0])
