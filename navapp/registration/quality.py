"""Fit quality: is any data feature still far from the registered model?

After LIBR every feature's residual RMS is compared with what its data noise allows. The
surgeon cannot see the truth; a feature that stays several millimetres off the deformed
model after convergence (a wrong basin, data from another organ, mislabelled landmarks)
is the one sign of a wrong answer the registration itself can give, so it is reported in
one line (``FitQuality.warning``) by the CLI, in ``result.json`` and on the
``Registration`` object for the viewer.
"""

from dataclasses import dataclass, field

from ..features import TABLE

# Expected RMS of the data's own error per feature (mm; ``Feature.noise_mm`` says why)
EXPECTED_NOISE_MM = {f.name: f.noise_mm for f in TABLE}
# A feature is flagged when its RMS exceeds noise + MARGIN_MM: the linear-elastic basis
# does not reach every detail of a true deformation, so a correct fit keeps some
# residual. Calibrated on the nine simulated study cases (noise-free data, so what stays is
# model mismatch): see docs/decisions/registration.md, "Registration: robust initialisation and fit quality".
MARGIN_MM = 2.0
MIN_POINTS = 5  # fewer points say too little to raise an alarm


@dataclass
class FeatureFit:
    """Residual of one data feature after the fit."""
    name: str
    n: int  # points
    rms_mm: float  # RMS point-to-model distance (Table I's f)
    allowed_mm: float  # the RMS above which it is flagged
    flagged: bool


@dataclass
class FitQuality:
    """Per-feature residuals against expected noise, and one line for the user."""
    features: list[FeatureFit] = field(default_factory=list)

    @property
    def flagged(self) -> list[str]:
        return [f.name for f in self.features if f.flagged]

    @property
    def ok(self) -> bool:
        return not self.flagged

    @property
    def warning(self) -> str | None:
        """One line naming the features left far off, or None when the fit is plausible."""
        bad = [f for f in self.features if f.flagged]
        if not bad:
            return None
        parts = ", ".join(f"{f.name} {f.rms_mm:.1f} mm RMS (expected ≤ {f.allowed_mm:.1f})" for f in bad)
        return (f"poor fit: {parts} after convergence — the result may be wrong; "
                f"check the labels and the initial pose, or add data")

    def as_dict(self, verdict: "Verdict | None" = None) -> dict:
        """``ok``: the answer's ``verdict`` when given (a result's one rule), else the residuals'
        own; ``residuals_ok``: the residuals' own, always."""
        return {"ok": self.ok if verdict is None else verdict.ok, "residuals_ok": self.ok, "warning": self.warning,
                "features": {f.name: {"n": f.n, "rms_mm": round(f.rms_mm, 3), "allowed_mm": f.allowed_mm,
                                      "flagged": f.flagged} for f in self.features}}


@dataclass(frozen=True)
class Verdict:
    """Is the answer fine, as far as navapp can tell: one rule, and it is "no warning". Every
    doubt about a registration — a pose the data cannot fix, too little of the liver covered,
    a deformation the data do not support, residuals beyond their noise, a target far from
    any data — is a line in ``warnings``; ``ok`` is true only when there is none. (The
    residual check alone, ``FitQuality.ok``, said "ok" beside a warning that the pose was
    not determined: two rules, and the wrong one was read first.)"""

    warnings: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return not self.warnings

    @classmethod
    def of_result(cls, summary: dict) -> "Verdict":
        """The verdict of a ``result.json`` (parsed), whichever navapp wrote it: older ones have
        no top-level ``ok``, their ``fit_quality.ok`` judged the residuals alone, and the
        oldest carry ``warning`` (lines joined by "; ") without ``warnings``."""
        lines = summary.get("warnings")
        if lines is None:
            joined = summary.get("warning")
            lines = joined.split("; ") if joined else []
        fit = summary.get("fit_quality") or {}
        if not lines and fit.get("ok") is False:
            lines = [fit.get("warning") or "poor fit"]
        return cls(tuple(lines))


def assess_fit(features: dict, noise_mm: dict | None = None, margin_mm: float = MARGIN_MM) -> FitQuality:
    """Fit quality from LIBR's per-feature statistics (``LibrResult.features``: name →
    {"n", "rms_mm", …}; the strain-energy entry is skipped). ``noise_mm`` overrides
    ``EXPECTED_NOISE_MM`` per feature (e.g. a tracker with known accuracy)."""
    noise = dict(EXPECTED_NOISE_MM, **(noise_mm or {}))
    out = []
    for name, st in features.items():
        if "rms_mm" not in st:
            continue
        allowed = noise.get(name, 1.0) + margin_mm
        out.append(FeatureFit(name, st["n"], st["rms_mm"], allowed, st["n"] >= MIN_POINTS and st["rms_mm"] > allowed))
    return FitQuality(out)
