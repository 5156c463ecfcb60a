"""Contours drawn by hand on a tracked ultrasound image, turned into registration data.

A click in the viewer is a ray; it meets the image plane at a pixel (``probe.ray_to_pixel``).
The vertices a user places form a polyline in pixel space, rasterised with the same
Bresenham routine the simulator uses, so drawn and simulated contours are sampled alike
(one point per pixel along the line). Pixels go to tracker space through the probe
calibration and the plane's tracked pose. No viser here.
"""

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from ..geometry.bresenham import polyline
from ..registration.objective import Rejection
from ..simulation.probe import Probe, pixels_to_tracker, ray_to_pixel

CENTERLINE_OF = {"portal_contour": "portal_centerline", "hepatic_contour": "hepatic_centerline"}
MIN_CENTROID_PIXELS = 6  # a closed contour smaller than this gives no centerline point (as in simulation)
MIN_RING_VERTICES = 4  # a closed vessel contour with fewer clicks has no shape to judge a stray one by


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


class OriginKind(Enum):
    """Where a registration data point came from."""

    STYLUS = "stylus"  # the simulated stylus sweep
    LIVE = "live"  # digitised with a tracked stylus
    PLANE = "plane"  # an added plane's segmentation
    CONTOUR = "contour"  # a contour drawn by hand
    SOURCE = "source"  # a simulated data source's acquisition (``simulation.sources``)


@dataclass(frozen=True, eq=False)
class Origin:
    """One data point's origin, so that a point the fit leaves far off can be named and
    removed: for a drawn contour the contour and the rasterised pixel (col, row) it came
    from (None: the contour's centerline point), else the plane index (PLANE) or nothing."""

    kind: OriginKind
    contour: "Contour | None" = None
    pixel: tuple[int, int] | None = None
    plane: int | None = None

    def vertex(self) -> int | None:
        """Index of the drawn vertex this point is the pixel of (a contour's point), or None
        for a point between vertices (the line joining two clicks) or another origin."""
        if self.contour is None or self.pixel is None:
            return None
        return next((i for i, v in enumerate(self.contour.vertices) if tuple(v) == self.pixel), None)


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


@dataclass(frozen=True, eq=False)
class StrayVertex:
    """A drawn vertex left out of the fit before it runs (``stray_vertices``): its point
    (tracker mm) and origin, so that the worst-points list can name it."""

    feature: str
    point: np.ndarray  # (3,) tracker mm
    origin: Origin


def stray_vertices(probe: Probe, contour: Contour, rejection: Rejection | None = None) -> list[int]:
    """Indices of the vertices of a closed vessel contour that lie off its lumen: their
    in-plane distance (mm) from the vertices' median centre beyond the fit's own outlier cut
    (``Rejection.beyond``: max(10 mm, 5 × the median distance)). The fit's residual cannot
    find such a vertex: its spike of pixels meets another branch of the vessel tree within a
    few mm (a portal vertex moved 35 mm: every spike point 8.8 mm or nearer, the fit dragged
    5.3 → 9.3 mm mean), and the contour's centre, one point with its feature's whole weight,
    moves onto that branch. ``rejection``: the cut's rule (default: the viewer fit's, ``Rejection()``)."""
    if contour.feature not in CENTERLINE_OF or not contour.closed or len(contour.vertices) < MIN_RING_VERTICES:
        return []
    v = np.asarray(contour.vertices, float) * probe.spacing_mm
    radius = np.linalg.norm(v - np.median(v, axis=0), axis=1)
    return [int(i) for i in np.flatnonzero((rejection or Rejection()).beyond(radius))]


def contour_points(probe: Probe, probe_to_tracker, contour: Contour, origins: dict | None = None,
                   left_out: list | None = None) -> dict:
    """Registration data from one contour: {feature: (N, 3) mm tracker points}, plus one
    centerline point (the in-plane centroid of the rasterised pixels, as the simulator
    does) for a closed vessel contour of at least ``MIN_CENTROID_PIXELS`` pixels. A stray
    vertex of a vessel contour (``stray_vertices``) is left out: the contour is rasterised
    through its neighbours. ``origins``: filled with {feature: [Origin] per point};
    ``left_out``: appended a ``StrayVertex`` per vertex left out."""
    stray = stray_vertices(probe, contour)
    if stray:
        if left_out is not None:
            for i in stray:
                c, r = contour.vertices[i]
                left_out.append(StrayVertex(contour.feature, pixels_to_tracker(probe, probe_to_tracker, [c], [r])[0],
                                            Origin(OriginKind.CONTOUR, contour, (int(c), int(r)), contour.plane)))
        kept = Contour(contour.plane, contour.feature,
                       [v for i, v in enumerate(contour.vertices) if i not in stray], contour.closed)
        cols, rows = contour_pixels(kept)
    else:
        cols, rows = contour_pixels(contour)
    if len(cols) == 0:
        return {}
    out = {contour.feature: pixels_to_tracker(probe, probe_to_tracker, cols, rows)}
    cl = CENTERLINE_OF.get(contour.feature)
    if cl is not None and contour.closed and len(cols) >= MIN_CENTROID_PIXELS:
        out[cl] = pixels_to_tracker(probe, probe_to_tracker, [cols.mean()], [rows.mean()])
    if origins is not None:
        origins[contour.feature] = [Origin(OriginKind.CONTOUR, contour, (int(c), int(r)), contour.plane)
                                    for c, r in zip(cols, rows, strict=True)]
        if cl in out:
            origins[cl] = [Origin(OriginKind.CONTOUR, contour, None, contour.plane)]
    return out
