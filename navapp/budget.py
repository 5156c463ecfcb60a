"""Memory budget: inputs are sized up before any work starts, and what would not fit in
this machine's memory is refused in one line saying what to do.

The budget is the memory available now (``psutil``), or ``$NAVAPP_MEMORY_MB``. The costs
are measured (docs/decisions/house.md, "Bounded resources"): a mesh node costs its share of the
deformation basis, a data point its share of a registration, a surface triangle its share
of the clean-up checks.
"""

import os

from .defaults import K
from .errors import InputError, NavappError

# expected tet-mesh nodes = volume / (NODES_PER_EDGE3 · edge³), fitted on the phantoms; its
# reasoning is with the mesher (anatomy/meshing.py), which reads it from here
NODES_PER_EDGE3 = 1.24

BASE_MB = 400.0
"""The interpreter with navapp's libraries loaded, before any case data."""

MB_PER_NODE = 0.045
"""Peak memory per mesh node of mesh + basis at k = 45 (precompute benchmark: 830 MB at
18,563 nodes, 1,157 MB at 26,390)."""

MB_PER_NODE_PER_K = 0.00035
"""How the peak per mesh node grows with each control point beyond k = 45: ``precompute --k 500``
on the 18,563-node demo mesh peaked at 4.2 GB against 830 MB at k = 45, (0.204 − 0.045) / 455."""

MB_PER_POINT = 0.016
"""Peak memory per intraoperative data point during a registration, k = 45: 500,000 points
were past 5.95 GB and still growing (> 11.1 KB a point) when stopped after 15 min, 1,000,000
reached an 8 GB limit in 85 s; 16 KB is that lower bound with a margin (10 KB before, under
which the advice "subsample to N points" named a count that would not fit)."""

MB_PER_TRIANGLE = 0.009
"""Peak memory per input surface triangle while reading and cleaning it up. It grows with
the count (self-intersection and manifold checks): 1.6 KB a triangle at 81,920 and 2.8 KB
at 327,680 (measured), 8.8 KB at 2 million (17.6 GB, not finished): the largest is used."""

FRACTION = 0.8  # of the available memory navapp plans to use: the rest is for the system and the viewer


def available_mb() -> float:
    """Memory navapp may plan with, MB: ``$NAVAPP_MEMORY_MB`` or 80 % of what is available now."""
    value = os.environ.get("NAVAPP_MEMORY_MB")
    if value:
        try:
            mb = float(value)
        except ValueError:
            raise NavappError(f"NAVAPP_MEMORY_MB={value!r} is not a number of megabytes") from None
        if not mb > 0:
            raise NavappError(f"NAVAPP_MEMORY_MB={value!r} must be positive")
        return mb
    import psutil

    return FRACTION * psutil.virtual_memory().available / 2 ** 20


def _gb(mb: float) -> str:
    # under 1 GB in MB: a need of 430 MB against 420 MB free read "0.4 GB, more than the 0.4 GB"
    return f"{mb:.0f} MB" if mb < 1024 else f"{mb / 1024:.1f} GB"


def check_mesh(nodes: int, edge: float, volume_mm3: float, setting: str = "--edge", path=None):
    """Refuse a mesh of about ``nodes`` nodes (from the liver's volume and ``edge``) whose
    basis would not fit, naming the finest edge that would. ``setting``: what set ``edge``,
    a command option ("--edge") or a scene key ("deformation.mesh_edge_mm"), named in the
    advice; ``path``: the file that holds it, named first (a scene file)."""
    budget = available_mb()
    need = BASE_MB + MB_PER_NODE * nodes
    if need <= budget:
        return
    fits = max(1.0, (budget - BASE_MB) / MB_PER_NODE)
    finest = _ceil((volume_mm3 / (NODES_PER_EDGE3 * fits)) ** (1 / 3))
    advice = f"use {setting} {finest} or coarser" if setting.startswith("-") else \
        f"set {setting} = {finest} or coarser"
    raise InputError(f"a mesh at {edge:g} mm would have about {nodes:,} nodes and need about {_gb(need)}, "
                     f"more than the {_gb(budget)} this machine has free: {advice}", path)


def check_basis(nodes: int, k: int):
    """Refuse a deformation basis of ``k`` control points on ``nodes`` mesh nodes that would
    not fit, naming the largest k that would (``check_mesh`` sizes the mesh at the default k)."""
    budget = available_mb()
    need = BASE_MB + nodes * (MB_PER_NODE + MB_PER_NODE_PER_K * (k - K))
    if need <= budget:
        return
    fits = K + ((budget - BASE_MB) / max(nodes, 1) - MB_PER_NODE) / MB_PER_NODE_PER_K
    advice = f"use --k {int(fits)} or fewer, or a coarser --edge" if fits >= 1 else "use a coarser --edge"
    raise NavappError(f"a deformation basis of k = {k} on {nodes:,} mesh nodes would need about {_gb(need)}, more "
                      f"than the {_gb(budget)} this machine has free: {advice}")


def _over(n: int, mb_each: float) -> tuple[float, float, int] | None:
    """(MB needed, MB free, how many would fit) when ``n`` items of ``mb_each`` exceed the budget; else None."""
    budget = available_mb()
    need = BASE_MB + mb_each * n
    if need <= budget:
        return None
    return need, budget, int((budget - BASE_MB) / mb_each)


def check_points(n: int, path):
    """Refuse ``n`` data points in one file beyond what a registration can hold."""
    over = _over(n, MB_PER_POINT)
    if over is None:
        return
    need, budget, fits = over
    raise InputError(f"{n:,} points would need about {_gb(need)} to register, more than the {_gb(budget)} "
                     f"this machine has free: subsample to at most {fits:,} points (e.g. every "
                     f"{_ordinal(-(-n // max(fits, 1)))} row)", path)


def check_triangles(n: int, path):
    """Refuse a surface of ``n`` triangles beyond what reading and cleaning it can hold."""
    over = _over(n, MB_PER_TRIANGLE)
    if over is None:
        return
    need, budget, fits = over
    raise InputError(f"{n:,} triangles would need about {_gb(need)}, more than the {_gb(budget)} this machine "
                     f"has free: decimate it to at most {fits:,} triangles (the mesher remeshes the surface at "
                     "the edge length anyway)", path)


def _ordinal(n: int) -> str:
    """2 → "2nd", 11 → "11th", 23 → "23rd"."""
    suffix = "th" if n % 100 in (11, 12, 13) else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def _ceil(x: float) -> str:
    """``x`` rounded up to one decimal, as a CLI value."""
    import math

    return f"{math.ceil(x * 10) / 10:g}"
