"""What is known of the pose before the data: a Gaussian prior on LIBR's rigid parameters.

In the operating room the data rarely arrive in an unknown frame: a landmark or fiducial
registration, a tracker calibration or the session's previous registration puts them in the
preoperative frame to within a few millimetres and degrees. ``PosePrior`` says so, and adds
to Ω (eq. 7) the term

    Ω_P(β) = s_P · ( |τ − τ_c|² / σ_τ²  +  |θ − θ_c|² / σ_θ² ),      s_P = w_ref · u² · σ_F²,

about the given pose (τ_c = θ_c = 0 when the rigid stage is the given pose itself). Its rows
in LM's residual vector are f_P = ((τ − τ_c) / σ_τ, (θ − θ_c) / σ_θ), each with weight s_P, so
its Jacobian is constant: I / σ on τ and θ, zero on α (docs/design.md, "Pose prior").

The prior is on τ, θ, the tracker's registration, not on the organ's own motion: the
control-point modes can move the organ nearly rigidly at little strain energy, and a liver
pushed against its supports does move so. A prior on the rigid part of J_u α as well held
such a motion back (tool0-b, a 9.8 mm push: 8.2 mm TRE against 3.5 mm with τ, θ alone
held; docs/decisions/registration.md, "Pose prior").

Why s_P: Ω is a log-likelihood only up to a scale. The paper's w_F / N_F makes a feature's
term w_F u² × its mean-square residual, whatever its point count: a feature is one
observation, its points correlated (the model's misfit is spatially smooth, not white
noise). Read so, a unit-weight feature whose residuals are σ_F RMS costs w_ref u² σ_F², and
a pose one declared standard deviation away costs the same.

The scale σ_F is the data's own: the robust standard deviation (1.4826 × the median absolute
value) of the residuals the model leaves, floored at the features' expected noise. The rigid
stage estimates it from the distances to the undeformed model at its pose, refitted until it
settles; data a rigid motion explains (a tracker offset, with or without a dent under part
of them) leave little misfit at the right pose, so the prior yields to them, and a dent under
fewer than half of the points does not set it. The deformable fit then re-estimates it from
its own residuals, where the deformation is no longer misfit (``pipeline._settle_scale``). A
fixed σ_F = 1 mm shrank a declared 4 mm / 3° offset by half; the RMS in place of the median
held a declared 10° / 17 mm offset at 4°; the rigid stage's scale kept for the deformable fit
held declared tracker offsets part-way (docs/decisions/registration.md, "Pose prior").
"""

from dataclasses import dataclass

import numpy as np

FEATURE_SD_MM = 1.0
"""σ_F (mm) of a ``PosePrior`` made by hand: the residual RMS one unit-weight data feature is read
as carrying when Ω is read as a log-likelihood (module doc). ``register`` replaces it by the data's
own robust σ at the rigid stage's pose; a fixed 1 mm shrank a declared offset by half
(docs/decisions/registration.md, "Pose prior")."""

W_REF_SI = 1.0
"""w_ref (m⁻²): the weight of a unit data feature (eq. 7's anterior surface)."""


def likelihood_scale(unit_m: float = 1e-3, feature_sd_mm: float = FEATURE_SD_MM) -> float:
    """s_P = w_ref u² σ_F² (dimensionless, SI like Ω): Ω / s_P is −2 log-likelihood with each data
    feature read as one observation of σ_F RMS (module doc); ``unit_m``: metres per model unit."""
    return W_REF_SI * unit_m ** 2 * feature_sd_mm ** 2


@dataclass(frozen=True)
class PosePrior:
    """The given pose is right to within ``sd_mm`` (per axis, mm) and ``sd_deg`` (per axis,
    degrees): a Gaussian prior on τ and θ of eq. 8 about the rigid stage's pose.

    ``PosePrior(1.5, 1.5)``: a fiducial registration or a tracker calibration;
    ``PosePrior(15, 10)``: a tracker frame that may be off by that much. ``register`` with a
    prior starts at the given pose and searches no other (no multi-start ICP).
    """

    sd_mm: float
    sd_deg: float
    # where the given pose lies relative to the rigid stage's, (τ mm, θ rad) to first order:
    # zero when the rigid stage is the given pose; ``register`` moves the rigid stage to the
    # prior-weighted rigid fit and sets this to where the given pose is from there
    centre: tuple[float, ...] = (0.0,) * 6
    # σ_F (mm) of ``likelihood_scale``: ``register`` sets it to the data's RMS distance from the
    # undeformed model at the rigid stage's pose (module doc, "The scale")
    feature_sd_mm: float = FEATURE_SD_MM

    def __post_init__(self):
        for name in ("sd_mm", "sd_deg", "feature_sd_mm"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"PosePrior.{name} must be a positive number, not {v!r}")

    @property
    def sd_rad(self) -> float:
        return float(np.radians(self.sd_deg))

    def scale(self, unit_m: float = 1e-3) -> float:
        """s_P, the weight of each prior row in Ω (``likelihood_scale`` at ``feature_sd_mm``)."""
        return likelihood_scale(unit_m, self.feature_sd_mm)

    def jacobian(self, n_modes: int) -> np.ndarray:
        """∂f_P/∂β (6, 3k + 6), constant: zero on α, diag(1/σ_τ (mm), 1/σ_θ (rad)) on τ, θ."""
        J = np.zeros((6, n_modes + 6))
        J[:3, n_modes:n_modes + 3] = np.eye(3) / self.sd_mm
        J[3:, n_modes + 3:] = np.eye(3) / self.sd_rad
        return J

    def residual(self, J: np.ndarray, beta: np.ndarray) -> np.ndarray:
        """f_P (6,) = J β − the centre in units of σ; ``J`` from ``jacobian``."""
        c = np.asarray(self.centre, float)
        return J @ beta - np.concatenate([c[:3] / self.sd_mm, c[3:] / self.sd_rad])

    def as_dict(self) -> dict:
        return {"known": True, "sd_mm": self.sd_mm, "sd_deg": self.sd_deg}


def parse_pose_sd(values: list[str]) -> PosePrior | None:
    """``--pose-sd MM DEG`` → PosePrior; ``--pose-sd none`` → None (an unknown frame).
    Raises ValueError with one line for anything else."""
    if len(values) == 1 and values[0].lower() == "none":
        return None
    if len(values) != 2:
        raise ValueError("--pose-sd takes two numbers, MM DEG (e.g. --pose-sd 1.5 1.5), or 'none'")
    try:
        mm, deg = float(values[0]), float(values[1])
    except ValueError:
        raise ValueError(f"--pose-sd: {' '.join(values)!r} are not two numbers (MM DEG)") from None
    return PosePrior(mm, deg)


def declared_pose(settings: dict) -> PosePrior | None:
    """The case's ``[intraop.pose]`` (case.toml, checked by ``read_case``): its PosePrior when
    ``known = true``, else None (an unknown frame)."""
    pose = settings.get("intraop", {}).get("pose", {})
    return PosePrior(float(pose["sd_mm"]), float(pose["sd_deg"])) if pose.get("known", False) else None
