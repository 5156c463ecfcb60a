"""Where to put a tab's camera so that the liver is seen whole in the part of the 3D view the
panels leave free. No viser here.

The 2D ultrasound view is docked on the left, beside the 3D canvas; the control panel floats
over the canvas's right side. Centred in the canvas, the liver's hilum, vessels and second
tumour sat behind the control panel at 1600 × 1000, and at 1366 × 768 the 2D view (610 px) and
the panel left the 3D view a 350 px strip. So on a narrow window the 2D view is docked at its
native scale (1×), half as wide, and the camera's target is moved sideways until the liver's
centre projects to the middle of the part the panel leaves free, at a distance where the liver
fits there.
"""

from dataclasses import dataclass

import numpy as np

CONTROL_PANEL_PX = 24 * 16 + 24  # viser's "large" control panel (24 em) and its margins, on the right
DOCK_2D_PX = (610, 340)  # the 2D view docked at 2× and at 1× (its 256-pixel-wide image, the rulers, a margin)
NARROW_PX = 1500  # below this window width the 2D view is docked at 1×
FILL = 0.85  # the share of the free width (and of the height) the liver may take


@dataclass(frozen=True)
class Screen:
    """A tab's 3D canvas and what floats over its sides, px."""

    width_px: int
    height_px: int
    left_px: int = 0
    right_px: int = CONTROL_PANEL_PX

    @property
    def free_px(self) -> int:
        return max(self.width_px - self.left_px - self.right_px, 1)


def dock_width(window_px: int) -> int:
    """The 2D view's dock width for a window this wide."""
    return DOCK_2D_PX[0] if window_px >= NARROW_PX else DOCK_2D_PX[1]


def project(points, position, target, up, fov_rad: float, screen: Screen) -> tuple[np.ndarray, np.ndarray]:
    """Pixel (x, y) of ``points`` (N, 3) mm in a pinhole camera at ``position`` looking at
    ``target`` (three.js's: vertical field of view, y down)."""
    f = np.asarray(target, float) - position
    f /= np.linalg.norm(f)
    right = np.cross(f, np.asarray(up, float))
    right /= np.linalg.norm(right)
    above = np.cross(right, f)
    rel = np.asarray(points, float) - position
    z = np.maximum(rel @ f, 1e-6)
    scale = screen.height_px / 2 / np.tan(fov_rad / 2)
    return screen.width_px / 2 + scale * (rel @ right) / z, screen.height_px / 2 - scale * (rel @ above) / z


def frame(points, direction, up, fov_rad: float, screen: Screen) -> tuple[np.ndarray, np.ndarray]:
    """(camera position, look-at target), mm, to see ``points`` (N, 3) mm whole from
    ``direction`` (camera from target) with ``up`` up, through a vertical field of view
    ``fov_rad``, centred in the free part of ``screen``: from the organ's centre, the target
    moved sideways and the distance set by projecting the points and correcting (a few rounds:
    perspective makes the near side larger and, off the axis, further out)."""
    pts = np.asarray(points, float)
    up = np.asarray(up, float)
    d = np.asarray(direction, float)
    d /= np.linalg.norm(d)
    right = np.cross(-d, up)
    if np.linalg.norm(right) < 1e-9:  # looking along up: any right will do
        right = np.cross(-d, np.array([0.0, 1.0, 0.0]))
        up = np.cross(right, -d)
    right /= np.linalg.norm(right)
    above = np.cross(right, -d)
    target = (pts.min(0) + pts.max(0)) / 2
    dist = float(np.ptp(pts, axis=0).max()) / np.tan(fov_rad / 2)
    free_x = screen.left_px + screen.free_px / 2
    for _ in range(6):
        x, y = project(pts, target + d * dist, target, up, fov_rad, screen)
        mm_per_px = 2 * dist * np.tan(fov_rad / 2) / screen.height_px
        # centre the organ's on-screen box on the free part, then scale it to FILL of it
        target = target + right * ((x.max() + x.min()) / 2 - free_x) * mm_per_px \
            - above * ((y.max() + y.min()) / 2 - screen.height_px / 2) * mm_per_px
        grow = max((x.max() - x.min()) / (FILL * screen.free_px), (y.max() - y.min()) / (FILL * screen.height_px))
        dist *= grow
    return target + d * dist, target
