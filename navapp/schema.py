"""Allowed ranges of settings, derived from their names, so that a value that cannot mean
anything (a negative standard deviation, a dropout of 200 %, a gravity tilt of 720°) is
refused in one line with its range, and a key added later to a scene table is covered by
the rule of its name without being listed here.

A name's rule is its exact entry in ``NAMED``, else the first matching entry of
``SUFFIXES`` (``sd_…``, ``…_mm``, ``…_deg``, …); every float must also be finite.
"""

import math
from dataclasses import dataclass

from .defaults import N_PLANES
from .errors import InputError


@dataclass(frozen=True)
class Range:
    """lo ≤ value ≤ hi (``open_lo`` / ``open_hi``: strict); None: unbounded on that side."""

    lo: float | None = None
    hi: float | None = None
    open_lo: bool = False
    open_hi: bool = False

    def holds(self, value: float) -> bool:
        if self.lo is not None and (value < self.lo or (self.open_lo and value == self.lo)):
            return False
        return not (self.hi is not None and (value > self.hi or (self.open_hi and value == self.hi)))

    def describe(self) -> str:
        if self.hi is None:
            return f"{'>' if self.open_lo else '>='} {self.lo:g}"
        if self.lo is None:
            return f"{'<' if self.open_hi else '<='} {self.hi:g}"
        return f"in {'(' if self.open_lo else '['}{self.lo:g}, {self.hi:g}{')' if self.open_hi else ']'}"


NON_NEGATIVE = Range(0.0)
POSITIVE = Range(0.0, open_lo=True)

NAMED = {
    "phantom": NON_NEGATIVE,  # a phantom index
    # numpy's generators take no negative seed; the control-point k-means (scikit-learn) none above 2³² − 1
    "seed": Range(0.0, 2.0**32 - 1),
    "fraction": Range(0.0, 1.0, open_hi=True),  # dropout: all data dropped leaves a case with no data
    "coverage": Range(0.0, 1.0, open_lo=True),
    "planes": Range(0, N_PLANES),
    "gravity_tilt_deg": Range(0.0, 90.0),  # from posterior toward the released side (as scene.py checks it)
    "head_up_deg": Range(-90.0, 90.0, open_lo=True, open_hi=True),
    "rotation_deg": Range(0.0, 180.0),
    "mesh_edge_mm": POSITIVE,
    "truth_E_pa": POSITIVE,
    "stiffness_pa_per_mm": POSITIVE,  # a declared support's springs: zero would hold nothing
}
"""Exact names."""

SUFFIXES = (
    ("sd_", NON_NEGATIVE, "prefix"),  # standard deviations
    ("_deg", Range(-180.0, 180.0), "suffix"),
    ("_mm", NON_NEGATIVE, "suffix"),
    ("_px", NON_NEGATIVE, "suffix"),
    ("_pa", NON_NEGATIVE, "suffix"),
    ("ms", NON_NEGATIVE, "exact"),
)
"""Rules by the form of a name, tried in order when it has no exact entry."""


def range_for(name: str) -> Range | None:
    """The range a setting called ``name`` (its last dotted part) must lie in, or None."""
    leaf = name.rsplit(".", 1)[-1]
    if leaf in NAMED:
        return NAMED[leaf]
    for part, rule, how in SUFFIXES:
        if (how == "prefix" and leaf.startswith(part)) or (how == "suffix" and leaf.endswith(part)) or leaf == part:
            return rule
    return None


def check(name: str, value, path=None):
    """Raise ``InputError`` (one line naming ``name`` and its range) when ``value`` is a
    number outside the range of its name, or a float that is not finite."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    if isinstance(value, float) and not math.isfinite(value):
        raise InputError(f"{name} = {value!r} must be a finite number", path)
    rule = range_for(name)
    if rule is not None and not rule.holds(value):
        raise InputError(f"{name} = {value!r} is out of range: must be {rule.describe()}", path)


def check_tables(data: dict, path=None, prefix: str = ""):
    """``check`` every number in a parsed TOML document (tables and arrays of tables
    walked; keys named ``section.key`` and ``effects[i].key`` as the user wrote them)."""
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            check_tables(value, path, f"{name}.")
        elif isinstance(value, list):
            for i, item in enumerate(value):
                if isinstance(item, dict):
                    check_tables(item, path, f"{name}[{i}].")
        else:
            check(name, value, path)
