"""Target registration error (TRE): the one definition every stage, study and view uses.

The error at a target is the Euclidean distance between where a registration puts a
preoperative point and where that point truly is (Heiselman & Miga 2020, section III-B);
a case's TRE summarises those distances over its targets. Nothing here reads a truth: the
caller brings it, after the fit, so the solver still never sees it.
"""

from dataclasses import asdict, dataclass

import numpy as np


def point_errors(pred, truth) -> np.ndarray:
    """Per-target error, mm.

    Parameters
    ----------
    pred : (T, 3) array_like
        registered positions of the targets, mm.
    truth : (T, 3) array_like
        their true positions, same frame, mm.

    Returns
    -------
    (T,) ndarray
        ``|pred - truth|`` row by row, mm.
    """
    return np.linalg.norm(np.asarray(pred) - np.asarray(truth), axis=1)


def mean_tre(pred, truth) -> float:
    """Mean target registration error over the targets, mm (see ``point_errors``)."""
    return float(point_errors(pred, truth).mean())


@dataclass(frozen=True)
class TreStats:
    """A case's TRE summarised over its ``n`` targets (``tre_stats``), mm."""

    mean_mm: float
    sd_mm: float  # population standard deviation
    max_mm: float
    n: int

    def as_dict(self) -> dict:
        """``{"mean_mm", "sd_mm", "max_mm", "n"}``: result.json's ``tre_rigid`` / ``tre_deformable``."""
        return asdict(self)


def tre_stats(pred, truth) -> TreStats:
    """Summary of ``point_errors(pred, truth)`` (same parameters): mean, population SD and
    largest error (mm) and the number of targets."""
    d = point_errors(pred, truth)
    return TreStats(float(d.mean()), float(d.std()), float(d.max()), int(len(d)))
