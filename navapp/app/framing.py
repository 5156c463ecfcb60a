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

from ..geometry.transforms import apply

CONTROL_PANEL_PX = 24 * 16 + 24  # viser's "large" control panel (24 em) and its margins, on the right
DOCK_2D_PX = (610, 340)  # the 2D view docked at 2× and at 1× (its 256-pixel-wide image, the rulers, a margin)
NARROW_PX = 1500  # below this window width the 2D view is docked at 1×
FILL = 0.85  # the share of the free width (and of the height) the liver may take
FRAME_ROUNDS = 12  # rounds of ``frame``'s centring and scaling
STEP = 0.5  # the share of the centring correction taken each round
CLEARANCE_MM = 20.0  # the camera stays this far in front of the nearest point it frames


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
    for _ in range(FRAME_ROUNDS):
        x, y = project(pts, target + d * dist, target, up, fov_rad, screen)
        mm_per_px = 2 * dist * np.tan(fov_rad / 2) / screen.height_px
        # centre the organ's on-screen box on the free part (half the way each round: a full
        # step overshot under perspective and swung from side to side on oblique views), then
        # scale it to FILL of it, the camera kept outside the organ (points behind it projected
        # to infinity, and the distance swung between far and inside)
        target = target + STEP * (right * ((x.max() + x.min()) / 2 - free_x) * mm_per_px
                                  - above * ((y.max() + y.min()) / 2 - screen.height_px / 2) * mm_per_px)
        grow = max((x.max() - x.min()) / (FILL * screen.free_px), (y.max() - y.min()) / (FILL * screen.height_px))
        dist = max(dist * grow, float(((pts - target) @ d).max()) + CLEARANCE_MM)
    return target + d * dist, target


PLANE_VIEW_MM = (320.0, (0.0, 80.0, 120.0))  # from the plane's front (its y axis) and a little above


def plane_view(probe_to_tracker, liver, fov_rad: float, screen: Screen | None,
               probe_mm=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """(camera position, look-at target), mm: an oblique view onto an image plane (its probe's
    pose, (4, 4), probe → tracker, mm) from the plane's front and a little above, framed like
    the home view: ``liver`` (N, 3) mm and the probe's body (a box ``probe_mm`` = (lateral,
    thickness, length behind the face), mm) whole, centred in the free part of ``screen``.
    Looking at the plane's centre from a fixed distance put it mid-canvas, and at
    1600 × 1000 the liver's far side was behind the control panel. Without a ``screen`` (the
    browser has not reported its size yet), that fixed view onto the plane's centre."""
    T = np.asarray(probe_to_tracker, float)
    front, lift = PLANE_VIEW_MM
    direction = T[:3, 1] * front + np.asarray(lift)
    if screen is None:
        centre = T[:3, 3] + T[:3, 2] * 40.0
        return centre + direction, centre
    w, t, length = probe_mm
    box = np.array([[sx * w / 2, sy * t / 2, -sz * length] for sx in (-1, 1) for sy in (-1, 1) for sz in (0, 1)])
    points = np.vstack([np.asarray(liver, float), apply(T, box)])
    return frame(points, direction, (0.0, 0.0, 1.0), fov_rad, screen)
