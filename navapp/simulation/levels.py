"""The paper's data levels from a simulated case folder: S, S + chosen planes, CBCT, iCT.

- "S": the stylus data (anterior, falciform, ridges);
- "S+planes": S plus the features of the chosen iUS planes (``intraop/us/plane_XX``);
- "CBCT": the full true anterior and posterior liver surface;
- "iCT": CBCT plus the full true vessel surfaces and centerlines.
Full surfaces are thinned to one point per ``spacing`` mm voxel.

The studies name their rows by ``LEVELS`` ("S+2": S and two planes, the planes given
apart); ``study_data`` reads the data of such a name, and the helpers below are the one
place that parses it.
"""

from pathlib import Path

import numpy as np

from ..anatomy.caseio import read_case, read_csv, read_surface
from ..anatomy.model import VESSELS
from ..errors import InputError
from ..features import STYLUS
from .stylus import thin

LEVELS = ("rigid", "S", "S+1", "S+2", "S+3", "S+all", "CBCT", "iCT")
"""The studies' data levels in the paper's Table II order: "rigid" (the stylus data, rigid
registration only), "S", "S+n" (S and n iUS planes), "S+all" (S and every plane), "CBCT", "iCT"."""


def plus_planes(n: int) -> str:
    """The level name of S and ``n`` iUS planes."""
    return f"S+{n}"


def has_planes(level: str) -> bool:
    """True for "S+n" and "S+all": S and iUS planes."""
    return level.startswith("S+")


def plane_count(level: str) -> int:
    """n of "S+n"."""
    if not has_planes(level) or level == "S+all":
        raise ValueError(f"{level!r} is not S + a number of planes")
    return int(level[2:])


def fixed_planes(level: str, n_planes: int) -> tuple[int, ...]:
    """The planes of a level that names them all or none: every one of the case's
    ``n_planes`` for "S+all", none for "rigid", "S", "CBCT" and "iCT". "S+n" leaves the
    choice of n planes to the study (``ValueError``)."""
    if level == "S+all":
        return tuple(range(n_planes))
    if has_planes(level):
        raise ValueError(f"{level!r} names how many planes, not which")
    return ()


def stylus_only_pose(level: str) -> bool:
    """True for the levels whose rigid stage sees only the stylus data (``registration.rigid``
    fits the surface features, which are the stylus's for S and every S + planes), so one
    rigid ICP serves all of a case's S and S + planes rows."""
    return level == "S" or has_planes(level)


def study_data(case_dir, level: str, planes=(), case=None, stylus=None) -> dict:
    """The data of a study level (``LEVELS``): "rigid" and "S" the stylus data (``stylus``
    when given, for a caller that reads it once per case), "S+n" and "S+all" S and
    ``planes``, "CBCT" and "iCT" the full surfaces."""
    if level in ("rigid", "S"):
        return data_level(case_dir, "S", case=case) if stylus is None else stylus
    if has_planes(level):
        return data_level(case_dir, "S+planes", planes=planes, case=case)
    return data_level(case_dir, level, case=case)


def data_level(case_dir, level: str, planes=(), spacing=3.0, case=None) -> dict:
    """Intraoperative data (feature → (N, 3) mm) of ``level`` for a simulated case."""

    case_dir = Path(case_dir)
    case = case or read_case(case_dir)
    if level == "S":
        return {k: v for k, v in case.intraop.items() if k in STYLUS}
    if level == "S+planes":
        out = data_level(case_dir, "S", case=case)
        for i in planes:
            pdir = case_dir / "intraop" / "us" / f"plane_{int(i):02d}"
            if not pdir.is_dir():
                raise InputError(f"no plane {i} in this case", pdir)
            for f in sorted(pdir.glob("*.csv")):
                pts = read_csv(f, ("x", "y", "z"))
                out[f.stem] = np.vstack([out[f.stem], pts]) if f.stem in out else pts
        return out
    if level in ("CBCT", "iCT"):
        tdir = case_dir / "truth"
        liver, _ = read_surface(tdir / "liver.ply", closed=False)
        regions = case.preop.regions
        ant = np.isin(regions, [0, 2, 3, 4])  # anterior, falciform and the ridges are all anterior
        out = {"anterior": thin(np.asarray(liver.vertices)[ant], spacing),
               "posterior": thin(np.asarray(liver.vertices)[~ant], spacing)}
        if level == "iCT":
            for v in VESSELS:
                p = tdir / f"{v}.ply"
                if p.exists():
                    out[f"{v}_contour"] = thin(np.asarray(read_surface(p, closed=False)[0].vertices), spacing)
                c = tdir / f"{v}_centerline.csv"
                if c.exists():
                    out[f"{v}_centerline"] = read_csv(c, ("x", "y", "z", "branch"), integer_last=True)[:, :3]
        return out
    raise InputError(f"unknown data level {level!r} (S, S+planes, CBCT, iCT)")
