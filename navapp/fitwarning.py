"""A warning about a registration's answer: one type from the check that finds it to every
place that shows it.

The solver's checks (too few points, too little coverage, the pose search, the pose's sliding
directions, the cross-validation, the fit's residuals, the predicted error over the organ, …)
each say what they found in one line; ``registration.pipeline.Registration`` gathers them as
``FitWarning``s of a ``WarningKind``, and decides which of them stand for the answer shown
(``Registration.warnings``), which say its pose is not to be believed
(``Registration.pose_doubts``), which a warm start carries from the fresh fit it continues
from (``Registration.carry``) and which says why an answer is its pose alone
(``Registration.why_pose_alone``). The command line, result.json, the viewer's run table,
red box, pinned banner and targets, the load study and Slicer's status line only show them:
they compare warnings, never search their words, and read no check's own line
(``tests/test_one_home.py``). Not a Python warning category (``errors.CarriedWarning`` is that): a
``FitWarning`` is data, kept with the answer.

It lives below every layer because tracking, which may not import the solver, shows them too.
"""

from collections.abc import Iterable
from dataclasses import dataclass
from enum import Enum


class WarningKind(Enum):
    """Which check found the warning."""

    FEW_POINTS = "few points"  # too few, collinear or out-of-scale data (``pipeline.undetermined_pose``)
    COVERAGE = "coverage"  # the data cover too little of the liver (``coverage.Coverage``)
    SAVED = "saved"  # a restored result's pinned line, read back from the viewer's session
    POSE_SEARCH = "pose search"  # the pose search's own doubt (``pose.PoseChoice``)
    UNDETERMINED_POSE = "undetermined pose"  # the data leave a motion free (``pose.Determinacy``)
    UNSUPPORTED = "unsupported deformation"  # the held-out prediction (``support.Support``)
    SURFACE_FORCES = "surface forces"  # the deformation chosen among none, basis and forces (``forces.ForceChoice``)
    SUPPORTS = "supports"  # the declared supports against the data (``forces.ForceChoice``)
    POOR_FIT = "poor fit"  # residuals against the expected noise (``quality.FitQuality``)
    ORGAN_ERROR = "organ error"  # the predicted error over the organ (``uncertainty.OrganError``)
    POSE_EVIDENCE = "pose evidence"  # a declared pose against the fitted one (``uncertainty.PoseEvidence``)
    TARGET = "target"  # the data near one target do not determine its deformation (``support.TargetSupport``)


@dataclass(frozen=True)
class FitWarning:
    """One warning: its ``kind`` and its ``text``, one line, as the user reads it.
    ``carried``: made at an earlier, full registration and carried to a warm start or a live
    frame, which did not repeat the check (the text says so; a consumer that shows it shorter
    reads this flag, never the text's words)."""

    kind: WarningKind
    text: str
    carried: bool = False

    @property
    def head(self) -> str:
        """The words before the first colon: what the warning is about, without its numbers."""
        return self.text.split(":", 1)[0].strip()

    def __str__(self) -> str:
        return self.text


def found(kind: WarningKind, text: str | None) -> list[FitWarning]:
    """``[FitWarning(kind, text)]``, or ``[]`` when a check found nothing (``text`` None or empty)."""
    return [FitWarning(kind, text)] if text else []


def texts(warnings: Iterable[FitWarning]) -> list[str]:
    """The warnings' lines, in order."""
    return [w.text for w in warnings]


def one_line(warnings: Iterable[FitWarning]) -> str | None:
    """The warnings as one line, each said once, "; " between them; None without any."""
    return "; ".join(dict.fromkeys(texts(warnings))) or None
