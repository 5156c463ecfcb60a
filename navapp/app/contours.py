"""Contours drawn by hand on a tracked ultrasound image, turned into registration data.

A click in the viewer is a ray; it meets the image plane at a pixel (``probe.ray_to_pixel``).
The vertices a user places form a polyline in pixel space, rasterised with the same
Bresenham routine the simulator uses, so drawn and simulated contours are sampled alike
(one point per pixel along the line). Pixels go to tracker space through the probe
calibration and the plane's tracked pose. No viser here.
"""

from dataclasses import dataclass, field

import numpy as np

from ..geometry.bresenham import polyline
from ..simulation.probe import Probe, pixels_to_tracker, ray_to_pixel

CENTERLINE_OF = {"portal_contour": "portal_centerline", "hepatic_contour": "hepatic_centerline"}
MIN_CENTROID_PIXELS = 6  # a closed contour smaller than this gives no centerline point (as in simulation)


@dataclass
class Contour:
    plane: int  # index of the plane it was drawn on
    feature: str  # a value of palette.DRAWABLE
    vertices: list = field(default_factory=list)  # [(col, row)] integer pixels, in drawing order
    closed: bool = False

    def to_json(self) -> dict:
        return {"plane": self.plane, "feature": self.feature, "vertices": [list(map(int, v)) for v in self.vertices],
                "closed": self.closed}

    @staticmethod
    def from_json(d: dict) -> "Contour":
        return Contour(int(d["plane"]), str(d["feature"]), [tuple(map(int, v)) for v in d["vertices"]],
                       bool(d["closed"]))


def click_to_pixel(probe: Probe, probe_to_tracker, origin, direction):
    """Integer pixel (col, row) where a click ray meets the image, or None if it misses
    the image (parallel, behind the camera, or outside its W × H pixels)."""
    hit = ray_to_pixel(probe, probe_to_tracker, np.asarray(origin, float), np.asarray(direction, float))
    if hit is None:
        return None
    col, row = int(round(hit[0])), int(round(hit[1]))
    if not (0 <= col < probe.width_px and 0 <= row < probe.height_px):
        return None
    return col, row


def contour_pixels(contour: Contour) -> tuple[np.ndarray, np.ndarray]:
    """Bresenham pixels (cols, rows) along the contour's polyline (closing segment included
    when closed), each pixel once, in raster order."""
    if not contour.vertices:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    rc = np.array([(r, c) for c, r in contour.vertices], np.int64)
    rows, cols = polyline(rc, closed=contour.closed)
    px = np.unique(np.column_stack([cols, rows]), axis=0)  # a closed loop revisits its first pixel
    return px[:, 0], px[:, 1]


def contour_points(probe: Probe, probe_to_tracker, contour: Contour) -> dict:
    """Registration data from one contour: {feature: (N, 3) mm tracker points}, plus one
    centerline point (the in-plane centroid of the rasterised pixels, as the simulator
    does) for a closed vessel contour of at least ``MIN_CENTROID_PIXELS`` pixels."""
    cols, rows = contour_pixels(contour)
    if len(cols) == 0:
        return {}
    out = {contour.feature: pixels_to_tracker(probe, probe_to_tracker, cols, rows)}
    cl = CENTERLINE_OF.get(contour.feature)
    if cl is not None and contour.closed and len(cols) >= MIN_CENTROID_PIXELS:
        out[cl] = pixels_to_tracker(probe, probe_to_tracker, [cols.mean()], [rows.mean()])
    return out
