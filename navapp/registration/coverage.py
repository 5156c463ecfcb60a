"""Does a registration's data cover enough of the liver for its pose to be believed?

A rigid pose from a small patch can be grossly wrong while fitting its data to a few tenths
of a millimetre: live 'Digitise as: anterior' for 15 s, then Rigid, gave a mean error of 48 mm
reported as "ICP RMS 3.69 mm"; one plane's posterior wall alone, 33–127 mm. The pose's
determinacy (``pose.pose_determinacy``) names the motions a patch leaves free, but only for the
stylus surface data, and a curved patch can fix every motion and still sit in the wrong place.
Coverage is the second check: the share of the liver's surface nodes within ``COVER_MM`` of a
data point (in the model frame). Measured on the demo liver (docs/decisions/registration.md, "Gross poses"):
the whole stylus sweep 21.8 %, its anterior 853 points 19.0 % (rigid error 8.9 mm mean), a
400-point patch 9.2 % (12.9 mm), 200 points 4.9 % (15.9 mm), one plane's wall ≤ 1.9 % (33–127 mm).

A declared pose (``prior.PosePrior``) is not a pose the data must find alone: where its posterior
says how far the pose may be off (``uncertainty.PoseEvidence``, ``OrganError.pose_mm``), ``register``
does not add this note beside it (docs/decisions/registration.md, "issue 46, session 35").
"""

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.spatial import cKDTree

from ..fitwarning import FitWarning, WarningKind, found
from .model import RegistrationModel

COVER_MM = 10.0  # a surface node this close to a data point counts as covered
MIN_COVERAGE = 0.10  # below this share of the liver surface the pose is not to be believed


@dataclass(frozen=True)
class Coverage:
    """The share of the liver surface the data cover (``fraction``, 0–1)."""

    fraction: float

    @property
    def warning(self) -> str | None:
        if self.fraction >= MIN_COVERAGE:
            return None
        return (f"the data cover {100 * self.fraction:.0f} % of the liver surface (within {COVER_MM:.0f} mm), less "
                f"than the {100 * MIN_COVERAGE:.0f} % a pose needs: the pose may be grossly wrong — do not rely "
                f"on it; digitise more of the surface")


def data_coverage(model: RegistrationModel, data_model_frame: dict) -> Coverage:
    """Coverage of the model's liver surface by data points in the model frame (feature → (N, 3) mm)."""
    pts = {name: np.asarray(p, float).reshape(-1, 3) for name, p in data_model_frame.items() if len(p)}
    if not pts or "liver" not in model.features:
        return Coverage(0.0)
    nodes = model.features["liver"].rest
    last = model.cache.coverage
    kept, covered = {}, np.zeros(len(nodes), bool)
    for name, Y in pts.items():
        kept[name] = entry = _feature_cover(nodes, Y, last.get(name))
        covered |= entry[3]
    model.cache.coverage = kept  # replaced whole: a registration in another thread reads either
    return Coverage(float(np.mean(covered)))


def _feature_cover(nodes, Y, last):
    """(Y, L, nodes covered by Y[:L], nodes covered by Y) for one feature's points.

    The exact rule, computed again only for the rows that changed: re-registration per
    ultrasound frame passes the kept data (stylus, frozen planes) first and the newest frame's
    rows after them, in the same pose, so the rows of the last call that the new ones start
    with (the length L) keep their nodes. A node is covered by the union of two sets of points
    iff by one of them, so the answer is that of ``_cover(nodes, Y)`` whole."""
    if last is None:
        return (Y.copy(), len(Y), *(2 * (_cover(nodes, Y),)))
    old, L, head, whole = last
    if old.shape == Y.shape and np.array_equal(old, Y):
        return last
    n = min(len(old), len(Y))
    diff = np.flatnonzero(np.any(old[:n] != Y[:n], axis=1))
    m = int(diff[0]) if len(diff) else n  # rows the two share from the start
    if m < L:  # the shared start is shorter than the kept one: keep the shorter one from now on
        L, head = m, _cover(nodes, Y[:m])
    return Y.copy(), L, head, head | _cover(nodes, Y[L:], skip=head)


def _cover(nodes, Y, skip=None) -> np.ndarray:
    """Nodes (V,) bool within ``COVER_MM`` of a point of Y; ``skip``: nodes known covered. Only
    the nodes inside Y's bounding box grown by ``COVER_MM`` can be (a node outside it is farther
    than that along one axis), so a frame's few hundred points look at a part of the surface."""
    out = np.zeros(len(nodes), bool)
    if not len(Y):
        return out
    near = np.all((nodes > Y.min(0) - COVER_MM) & (nodes < Y.max(0) + COVER_MM), axis=1)
    if skip is not None:
        near &= ~skip
    idx = np.flatnonzero(near)
    if len(idx):
        d, _ = cKDTree(Y).query(nodes[idx], distance_upper_bound=COVER_MM)
        out[idx] = d < COVER_MM
    return out


def _kept_covers_enough(model: RegistrationModel, data_model_frame: dict) -> bool:
    """True when the rows these data share with the last call's (all of them, or
    ``_feature_cover``'s kept start) already cover ``MIN_COVERAGE``: coverage only grows with points, so the whole data
    cover at least that and no warning can follow. A live update changes only the newest
    frame's rows, whose nodes then need no search (~1 ms a frame)."""
    if "liver" not in model.features:
        return False
    covered = None
    last = model.cache.coverage
    for name, Y in data_model_frame.items():
        entry = last.get(name)
        if entry is None:
            continue
        old, L, head, whole = entry
        Y = np.asarray(Y, float).reshape(-1, 3)
        if len(Y) >= len(old) and np.array_equal(old, Y[:len(old)]):
            known = whole  # the last call's rows, all of them, start these
        elif len(Y) >= L and np.array_equal(old[:L], Y[:L]):
            known = head
        else:
            continue
        covered = known.copy() if covered is None else covered | known
    return covered is not None and float(np.mean(covered)) >= MIN_COVERAGE


class Noted(Protocol):
    """What ``note_coverage`` reads and adds to: a ``pipeline.Registration`` (which calls it on
    every registration, so this module may not import it: the two would import each other)."""

    model: RegistrationModel
    data_model_frame: dict
    notes: list[FitWarning]


def note_coverage(reg: Noted) -> None:
    """Check ``reg``'s coverage and add its warning to the registration's notes (so that every
    reader of ``Registration.warnings`` — ``navapp register``, result.json, the run table,
    Slicer's NavappStatus — carries it); idempotent. ``pipeline.register`` calls it on every
    registration it returns. ``data_coverage`` gives the share itself."""
    if _kept_covers_enough(reg.model, reg.data_model_frame):
        return
    cov = data_coverage(reg.model, reg.data_model_frame)
    for w in found(WarningKind.COVERAGE, cov.warning):
        if w not in reg.notes:
            reg.notes.append(w)
