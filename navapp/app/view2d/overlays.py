"""What the 2D ultrasound view draws over the B-mode image: the model's liver boundary,
portal and hepatic veins (and targets) cut by the image plane, in image pixels.

A mesh in tracker space is cut by the plane of a tracked frame (the probe's y axis is the
plane normal, ``probe.tracker_to_pixels``) with the exact section of
``geometry.planes.plane_section``; each cut segment's two ends are projected to
continuous pixel coordinates (col, row). Segments are kept as they are (not chained into
polylines): the canvas draws each, and the parts outside the W × H image are clipped by
the canvas itself. No viser here.
"""

from dataclasses import dataclass

import numpy as np

from ...geometry.planes import plane_section
from ...simulation.probe import Probe, tracker_to_pixels


@dataclass
class Overlay:
    """One object cut by the image plane."""

    name: str  # e.g. "portal (registered)"
    colour: str  # CSS colour
    dashed: bool  # preoperative (rigidly placed) outlines are dashed, registered ones solid
    segments: np.ndarray  # (S, 2, 2) float pixel coordinates (col, row) of each cut segment's ends

    def to_json(self) -> dict:
        return {"name": self.name, "colour": self.colour, "dashed": self.dashed, "visible": True,
                "segments": np.round(self.segments.reshape(-1, 4), 2).tolist()}


def section_pixels(probe: Probe, probe_to_tracker, vertices, faces) -> np.ndarray:
    """(S, 2, 2) pixel coordinates (col, row) of the plane ∩ mesh segments of a triangle
    mesh given in tracker space (vertices (V, 3) mm, faces (F, 3) int); only segments
    with at least one end within the image's depth range and a margin beside it."""
    T = np.asarray(probe_to_tracker, float)
    v = np.asarray(vertices, float)
    # a cheap reject first: only triangles near the image rectangle can cut it there
    cols, rows, off = tracker_to_pixels(probe, T, v)
    reach = np.abs(off) < 50.0
    f = np.asarray(faces)
    f = f[reach[f].any(1)]
    if len(f) == 0:
        return np.zeros((0, 2, 2))
    seg = plane_section(v, f, T[:3, 3], T[:3, 1])
    if len(seg) == 0:
        return np.zeros((0, 2, 2))
    c, r, _ = tracker_to_pixels(probe, T, seg.reshape(-1, 3))
    px = np.column_stack([c, r]).reshape(-1, 2, 2)
    margin = 20.0
    inside = ((px[..., 0] > -margin) & (px[..., 0] < probe.width_px + margin)
              & (px[..., 1] > -margin) & (px[..., 1] < probe.height_px + margin)).any(1)
    return px[inside]


def polyline_length_mm(probe: Probe, segments: np.ndarray) -> float:
    """Total length (mm) of pixel segments (S, 2, 2), for tests and the panel."""
    if len(segments) == 0:
        return 0.0
    return float(np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1).sum() * probe.spacing_mm)
