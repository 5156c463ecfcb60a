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
# model mismatch): see docs/decisions.md, "Registration: robust initialisation and fit quality".
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

    def as_dict(self) -> dict:
        return {"ok": self.ok, "warning": self.warning,
                "features": {f.name: {"n": f.n, "rms_mm": round(f.rms_mm, 3), "allowed_mm": f.allowed_mm,
                                      "flagged": f.flagged} for f in self.features}}


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
