"""The tracked ultrasound probe, shown and kept: its latest frame drawn on the probe, the live
re-registration told of each new one, and the frame frozen as a plane of the session."""

import numpy as np

from ...geometry.transforms import probe_pose
from ...simulation.ultrasound import PlaneData
from ...tracking.events import ProbeSample, ToolStatus
from ..imaging import LIVE_PLANE_BASE
from ..state import Change
from .base import Wiring, shows


def probe_pose_from_image(image_to_reference, width_px, height_px) -> tuple[np.ndarray, float]:
    """navapp's ProbeToTracker (4×4, rigid: x lateral, y plane normal, z depth, origin at
    the centre of the probe face) and the pixel spacing (mm) of a frame whose
    ImageToReference maps (col, row, 0, 1) to mm; inverse of ``Probe.image_to_probe``."""
    m = np.asarray(image_to_reference, float)
    a, b, o = m[:3, 0], m[:3, 1], m[:3, 3]  # a column step, a row step (mm), pixel (0, 0)
    return probe_pose(o + a * (width_px - 1) / 2.0, a, b), float(np.linalg.norm(a))


class ProbeShown:
    """The iUS probe's ``LiveSource``. ``frame``: the latest tracked frame on show (None: none
    yet, or its stream — the image's, and the probe's pose where it places it — is lost)."""

    source = "ius"

    def __init__(self, wiring: Wiring):
        self.client, self.core, self.new_frame = wiring.client, wiring.core, wiring.new_frame
        self.frame: ProbeSample | None = None

    def wakes(self, event: object) -> bool:
        return isinstance(event, ProbeSample)

    def show(self, now: float, status: dict[str, ToolStatus]) -> bool:
        f = self.client.latest_frame
        imaged = self.client.fresh(self.source, status)
        if f is not None and f is not self.frame and imaged:
            self.frame = f
            self.core.each_view(shows("show_live_frame", f))
            self.new_frame()
        elif not imaged and self.frame is not None:
            # a lost probe is not drawn at its last pose with its last image (nor frozen as a plane)
            self.frame = None
            self.core.each_view(shows("show_live_frame", None))
            self.core.each_view(lambda v: v.refresh(Change.LIVE))
        return False

    def age(self, status: dict[str, ToolStatus]) -> None:
        pass

    def taken(self) -> list[tuple[np.ndarray, list[str]]]:
        return []  # a frame is data once frozen and segmented (``Live.freeze_frame``), not as it arrives

    def freeze(self) -> int | str:
        """The frame on show becomes a plane of the session, kept: its image a PNG beside
        session.json, its pose in ``Session.live_planes``, the plane in ``Core.planes``.
        Returns its plane index, or why not (no frame now; a frame that is not the scene's probe's)."""
        core = self.core
        sd, session = core.need_scene()
        with core.lock:
            index = LIVE_PLANE_BASE + len(session.live_planes)
            plane = self.frozen_plane(index)
            f = self.frame
            if plane is None or f is None or plane.image is None:
                return "No live ultrasound frame now (none received yet, or the probe's stream is lost)."
            probe = sd.probe
            H, W = plane.image.shape[:2]
            spacing = f.spacing_mm
            if (H, W) != (probe.height_px, probe.width_px) or abs(spacing[0] - probe.spacing_mm) > 1e-6 \
                    or abs(spacing[1] - probe.spacing_mm) > 1e-6:
                return (f"the tracked frame is {W}×{H} px at {spacing[0]:.3f}×{spacing[1]:.3f} mm, the scene's "
                        f"probe {probe.width_px}×{probe.height_px} px at {probe.spacing_mm} mm: set the scene's probe")
            from PIL import Image

            rel = f"live/frame_{index - LIVE_PLANE_BASE:03d}.png"
            (session.folder / "live").mkdir(parents=True, exist_ok=True)
            Image.fromarray(plane.image).save(session.folder / rel)
            core.planes[index] = plane
            session.live_planes.append({"index": index, "pose": plane.probe_to_tracker.tolist(), "png": rel})
        return index

    def frozen_plane(self, index) -> PlaneData | None:
        """The latest frame as a plane of the session, or None (no frame yet)."""
        f = self.frame
        if f is None:
            return None
        img = np.asarray(f.image)
        T, _ = probe_pose_from_image(f.image_to_reference, img.shape[1], img.shape[0])
        return PlaneData(index, "live", T, {}, img.astype(np.uint8))


def make(wiring: Wiring) -> ProbeShown:
    return ProbeShown(wiring)
