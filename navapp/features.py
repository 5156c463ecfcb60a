"""The intraoperative data features: one record each, read by every module.

A data feature is one kind of intraoperative point (``intraop/<name>.csv``). Its record says
how the registration treats it (the residual ``kind`` of Table I, the model feature it
slides on, its weight w_F of eq. 7, paper §II-D), how it is acquired (tracked stylus, iUS
plane or fiducial), its expected noise for the fit-quality check and its colour in the
viewer. Everything that used to list features (case folders, the objective's weights, the
rigid ICP, the data levels, the simulator, the app) derives its list from ``TABLE``.
"""

from dataclasses import dataclass


@dataclass(frozen=True)
class Feature:
    """One intraoperative data feature.

    Attributes
    ----------
    name : str
        the file stem in ``intraop/`` and the key in every data dict.
    kind : str
        residual of Table I: ``"surface"`` (signed point–surface distance), ``"centerline"``
        (point–polyline) or ``"fiducial"`` (point–point, row by row).
    target : str
        the model feature it slides on (``RegistrationModel.features``): ``"liver"``, a
        labelled region (``"falciform"``, ``"ridge_left"``, ``"ridge_right"``), a vessel
        surface, a centerline or ``"fiducials"``.
    weight : float
        w_F of eq. 7, m⁻² (paper §II-D).
    source : str
        ``"stylus"`` (digitised on the anterior surface), ``"ius"`` (segmented from a tracked
        ultrasound plane), ``"fiducial"``, or the name of a source module in
        ``navapp/simulation/sources`` (``"laparoscope"``), which simulates and receives it.
    colour : tuple of int
        RGB 0–255 of its points in the viewer.
    noise_mm : float
        expected RMS of the data's own error (``registration.quality``): tracked stylus and
        iUS segmentation about 0.5 mm; a surgeon's falciform and ridge designations are
        approximate to a few mm; centerline points are contour centroids (≈1 mm).
    words : str
        what the viewer calls its points in a sentence ("portal-vein contours").
    """

    name: str
    kind: str
    target: str
    weight: float
    source: str
    colour: tuple[int, int, int]
    noise_mm: float
    words: str

    @property
    def salient(self) -> bool:
        """Slides on its own labelled region of the liver surface (falciform, ridges)."""
        return self.target in REGION_TARGETS


REGION_TARGETS = ("falciform", "ridge_left", "ridge_right")  # labelled liver-surface regions (anatomy.model)

TABLE: tuple[Feature, ...] = (
    Feature("anterior", "surface", "liver", 1.0, "stylus", (255, 255, 255), 0.5, "the anterior surface"),
    # lime, not yellow: the registered liver is drawn yellow (app.palette.REGISTERED, OVERLAY_STYLE)
    Feature("posterior", "surface", "liver", 1.0, "ius", (140, 255, 70), 0.5, "the posterior liver wall"),
    Feature("falciform", "surface", "falciform", 0.3, "stylus", (255, 0, 255), 1.5, "the falciform ligament"),
    Feature("ridge_left", "surface", "ridge_left", 0.3, "stylus", (0, 255, 255), 1.5, "the left inferior ridge"),
    Feature("ridge_right", "surface", "ridge_right", 0.3, "stylus", (0, 200, 200), 1.5, "the right inferior ridge"),
    Feature("portal_contour", "surface", "portal", 1.0, "ius", (255, 154, 31), 0.5, "portal-vein contours"),
    Feature("hepatic_contour", "surface", "hepatic", 1.0, "ius", (46, 230, 255), 0.5, "hepatic-vein contours"),
    Feature("portal_centerline", "centerline", "portal_centerline", 1.0, "ius", (255, 0, 0), 1.0,
            "portal-vein centres"),
    Feature("hepatic_centerline", "centerline", "hepatic_centerline", 1.0, "ius", (0, 60, 255), 1.0,
            "hepatic-vein centres"),
    Feature("fiducials", "fiducial", "fiducials", 1.0, "fiducial", (255, 255, 0), 0.5, "fiducials"),
    # depth noise grows with depth (sd 0.2 mm + 0.8 mm at 100 mm: simulation/sources/laparoscope.py)
    Feature("laparoscope", "surface", "liver", 1.0, "laparoscope", (255, 120, 200), 1.0,
            "the laparoscope's depth points"),
)
"""Every data feature, in the order files and tables list them."""

BY_NAME: dict[str, Feature] = {f.name: f for f in TABLE}
NAMES: tuple[str, ...] = tuple(f.name for f in TABLE)
"""The allowed ``intraop/<name>.csv`` stems."""
STYLUS: tuple[str, ...] = tuple(f.name for f in TABLE if f.source == "stylus")
"""Digitised with the tracked stylus: anterior, falciform, ridges (the paper's data level S)."""
SALIENT: tuple[str, ...] = tuple(f.name for f in TABLE if f.salient)
"""Salient features: each slides on its own labelled region."""
HAND_WIRED = ("fiducial",)
"""Sources with no module of ``navapp/simulation/sources``: fiducials, declared in a case,
neither simulated nor received. Every other ``source`` is a module there, simulated through
the protocol (the stylus, the iUS planes and their frames at a chosen pose, the laparoscope)."""
TRACKED = ("stylus", "ius")
"""Sources received as a tracked tool's pose stream, each by its own module of
``navapp/tracking/receivers`` and shown by its own module of ``navapp/app/sources`` (the
stylus's tip, its lost banner and the digitiser's points; the probe's tracked frames, drawn,
frozen and followed), not as points a POINT message carries."""
SOURCED: tuple[str, ...] = tuple(f.name for f in TABLE if f.source not in HAND_WIRED + TRACKED)
"""The features of those sources: live, an OpenIGTLink POINT message of this device name."""
SEEN: tuple[str, ...] = tuple(n for n in SOURCED if BY_NAME[n].kind == "surface" and BY_NAME[n].target == "liver")
"""Liver-surface points a registered source sees from outside the liver (the laparoscope's)."""
RIGID: tuple[str, ...] = STYLUS + ("fiducials",) + SEEN
"""The features that steer the rigid ICP (iUS data join only in the deformable stage)."""
LIVER_SURFACE: tuple[str, ...] = tuple(f.name for f in TABLE if f.kind == "surface" and
                                       (f.target == "liver" or f.salient))
"""Points on the liver's own surface (stylus and iUS posterior)."""


def weights_si() -> dict[str, float]:
    """Feature → w_F (m⁻²), a fresh dict (callers may change it)."""
    return {f.name: f.weight for f in TABLE}


def data_to_model() -> dict[str, str]:
    """Feature → the model feature it slides on."""
    return {f.name: f.target for f in TABLE}
