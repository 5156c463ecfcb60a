"""Acquisition effects, each a small function that runs only when a scene declares it.

Every function records itself in a ``Ledger`` when it runs, so a test (or a user) can see
exactly what a simulation did — and that an undeclared effect never ran.
"""

from dataclasses import dataclass, field

import numpy as np

from ..geometry.transforms import axis_angle, homogeneous


@dataclass(frozen=True)
class Effect:
    """One declared acquisition effect of a scene (``[[effects]]``): its kind and its
    parameters (``scene.EFFECT_PARAMS``)."""

    kind: str
    params: dict


@dataclass
class Ledger:
    """Names of the stages and effects that ran, in order, with how often."""

    ran: list = field(default_factory=list)

    def mark(self, name: str):
        self.ran.append(name)

    def count(self, name: str) -> int:
        return self.ran.count(name)


def tracking_noise(points, rng, ledger: Ledger, sd_mm: float):
    """Isotropic Gaussian tracker noise (mm) on every tracked point."""
    ledger.mark("tracking_noise")
    return points + rng.normal(scale=sd_mm, size=points.shape)


def calibration_error(probe_to_tracker, rng, ledger: Ledger, rotation_deg: float, translation_mm: float):
    """A wrong probe calibration: the pose used to map pixels to 3D is off by a random
    rigid transform of the given magnitudes (rotation about a random axis, shift along a
    random direction), in the probe's own frame."""
    ledger.mark("calibration_error")
    return probe_to_tracker @ homogeneous(*_random_rigid(rng, rotation_deg, translation_mm))


def _random_rigid(rng, rotation_deg: float, translation_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """A rotation of ``rotation_deg`` about a random axis (3, 3) and a shift of
    ``translation_mm`` along a random direction (3,), drawn in that order."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    shift = rng.normal(size=3)
    shift *= translation_mm / np.linalg.norm(shift)
    return axis_angle(axis, np.radians(rotation_deg)), shift


def tracker_offset(pivot, rng, ledger: Ledger, rotation_deg: float, translation_mm: float) -> np.ndarray:
    """The tracker frame is not the preoperative one: a 4 × 4 rigid transform, a rotation
    of ``rotation_deg`` about a random axis through ``pivot`` (3,) mm, then a shift of
    ``translation_mm`` along a random direction."""
    ledger.mark("tracker_offset")
    R, shift = _random_rigid(rng, rotation_deg, translation_mm)
    return homogeneous(R, np.asarray(pivot) - R @ np.asarray(pivot) + shift)


def probe_compression(points, contact, depth_axis, ledger: Ledger, depth_mm: float, radius_mm: float):
    """The probe indents the tissue it touches: points move along the probe's depth axis
    by depth·exp(−(r/R)²)·exp(−z/R), r the distance from the contact axis and z the depth
    below the contact point (a smooth, decaying indentation; not a contact simulation)."""
    ledger.mark("probe_compression")
    rel = points - contact
    z = np.clip(rel @ depth_axis, 0, None)
    r = np.linalg.norm(rel - np.outer(rel @ depth_axis, depth_axis), axis=1)
    w = depth_mm * np.exp(-(r / radius_mm) ** 2) * np.exp(-z / radius_mm)
    return points + np.outer(w, depth_axis)


def contour_jitter(cols, rows, rng, ledger: Ledger, sd_px: float):
    """Segmentation jitter: Gaussian noise (pixels) on contour pixel coordinates."""
    ledger.mark("contour_jitter")
    return cols + rng.normal(scale=sd_px, size=len(cols)), rows + rng.normal(scale=sd_px, size=len(rows))


def dropout(points, rng, ledger: Ledger, fraction: float):
    """Drop a random ``fraction`` of the points (lost tracking, shadowing)."""
    ledger.mark("dropout")
    keep = rng.random(len(points)) >= fraction
    return points[keep]
