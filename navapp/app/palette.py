"""Every colour and display word of the viewer, in one place: the 3D layers, the 2D view's
overlays and drawn contours, the legend, the names of drawable features and the words a
sentence uses for a data feature. Data colours and words come from ``features.TABLE``,
so a data point, the contour it was drawn as and its legend entry share one colour.
No viser here.
"""

from dataclasses import dataclass

from ..anatomy.model import VESSELS
from ..features import BY_NAME, TABLE

RGB = tuple[int, int, int]


def hex_colour(rgb: RGB) -> str:
    return "#{:02x}{:02x}{:02x}".format(*rgb)


# ---------------------------------------------------------------- 3D scene
LIVER: RGB = (205, 160, 140)
VESSEL: dict[str, RGB] = {"portal": (220, 50, 50), "hepatic": (60, 90, 220)}
TRUTH: RGB = (60, 200, 90)
REGISTERED: RGB = (240, 190, 60)
REG_VESSEL: dict[str, RGB] = {"portal": (200, 0, 0), "hepatic": (0, 60, 230)}
TARGET: RGB = (170, 60, 230)
REG_TARGET: RGB = (230, 0, 255)
SUPPORTS: RGB = (0, 160, 150)  # the surface the stated supports hold (preoperative model)
FEATURE_COLOURS: dict[str, RGB] = {f.name: f.colour for f in TABLE}  # data points, by feature
TURBO_CSS = "#30123b,#4686fb,#1ae4b6,#a2fc3c,#fabb39,#e4460a,#7a0403"  # the error colour scale (matplotlib turbo)
# the floating legend


@dataclass(frozen=True)
class LegendEntry:
    """One line of the floating legend: its words, its swatch's colour and opacity, and the
    layer it names where that layer is not always there (the ghost only with a truth, the
    supports only while stated): the line is left out while that layer draws nothing."""
    words: str
    colour: RGB
    opacity: float
    layer: str | None = None


LEGEND: tuple[LegendEntry, ...] = (
    LegendEntry("preop liver", LIVER, 0.5), LegendEntry("preop portal vein", VESSEL["portal"], 0.6),
    LegendEntry("preop hepatic veins", VESSEL["hepatic"], 0.6), LegendEntry("registered liver", REGISTERED, 0.7),
    LegendEntry("registered portal vein", REG_VESSEL["portal"], 1),
    LegendEntry("registered hepatic veins", REG_VESSEL["hepatic"], 1),
    LegendEntry("targets (tumours)", TARGET, 1),
    LegendEntry("true liver (ghost)", TRUTH, 0.5, layer="True deformed liver (ghost)"),
    LegendEntry("held at the stated supports", SUPPORTS, 1, layer="Stated supports"))

# ---------------------------------------------------------------- 2D view
# the model cut by the image: preoperative (rigidly placed) dashed in the first colour,
# registered solid in the second
OVERLAY_STYLE: dict[str, tuple[str, str]] = {
    "liver": ("#e0b090", "#ffd040"), "portal": ("#ff8080", "#ff2020"), "hepatic": ("#80a0ff", "#2f6bff"),
    "target": ("#c080ff", "#e000ff"),
}
WORST_POINT = "#ff2a2a"  # a drawn vertex in the worst-points list: ring and residual beside it
# the contour being drawn (page.js draws it; kept here so the words stay together): white, as
# yellow is the registered liver's colour
IN_PROGRESS = "#ffffff"

# ---------------------------------------------------------------- drawing
DRAWABLE: dict[str, str] = {  # what the user can designate on an image → the data feature it becomes
    "PV contour": "portal_contour",
    "HV contour": "hepatic_contour",
    "Posterior surface": "posterior",
}
DRAWN_COLOURS: dict[str, str] = {f: hex_colour(BY_NAME[f].colour) for f in DRAWABLE.values()}
VESSEL_SHORT: dict[str, str] = {f"{v}_contour": "PV" if v == "portal" else "HV" for v in VESSELS}


def feature_words(name: str) -> str:
    """A data feature as a sentence says it ("portal-vein contours")."""
    f = BY_NAME.get(name)
    return f.words if f is not None else name


def data_counts(data: dict) -> str:
    """The data's points per feature in words, in the features' table order ("anterior surface
    853, falciform ligament 30"): the Ultrasound panel listed the keys ("ridge_left 12,
    portal_centerline 1"); "none yet" without data."""
    order = {f.name: i for i, f in enumerate(TABLE)}
    parts = [f"{feature_words(k).removeprefix('the ')} {len(v):,}"
             for k, v in sorted(data.items(), key=lambda kv: (order.get(kv[0], len(order)), kv[0])) if len(v)]
    return ", ".join(parts) or "none yet"
