"""The paper's data levels from a simulated case folder: S, S + chosen planes, CBCT, iCT.

- "S": the stylus data (anterior, falciform, ridges);
- "S+planes": S plus the features of the chosen iUS planes (``intraop/us/plane_XX``);
- "CBCT": the full true anterior and posterior liver surface;
- "iCT": CBCT plus the full true vessel surfaces and centerlines;
- "S+<source>" (``SOURCE_LEVELS``): S plus the points of a registered data source
  (``simulation/sources``, e.g. "S+laparoscope"), for a case that has them.
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
from ..features import BY_NAME, SOURCED, STYLUS
from .sources import features_of
from .stylus import thin

SOURCES: tuple[str, ...] = tuple(dict.fromkeys(BY_NAME[n].source for n in SOURCED))
"""The registered data sources (``features.TABLE`` sources not wired by hand)."""
SOURCE_LEVELS: tuple[str, ...] = tuple(f"S+{s}" for s in SOURCES)
"""One level per registered source: S and that source's points ("S+laparoscope")."""
LEVELS = ("rigid", "S", "S+1", "S+2", "S+3", "S+all") + SOURCE_LEVELS + ("CBCT", "iCT")
"""The studies' data levels in the paper's Table II order: "rigid" (the stylus data, rigid
registration only), "S", "S+n" (S and n iUS planes), "S+all" (S and every plane), then a
level per registered source (not in the paper), "CBCT", "iCT"."""


def plus_planes(n: int) -> str:
    """The level name of S and ``n`` iUS planes."""
    return f"S+{n}"


def has_planes(level: str) -> bool:
    """True for "S+n" and "S+all": S and iUS planes."""
    return level == "S+all" or (level.startswith("S+") and level[2:].isdigit())


def source_of(level: str) -> str | None:
    """The data source of a source level ("S+laparoscope" → "laparoscope"), else None."""
    return level[2:] if level in SOURCE_LEVELS else None


def case_planes(case_dir) -> int:
    """How many iUS planes a case folder has (``intraop/us/plane_XX``)."""
    us = Path(case_dir) / "intraop" / "us"
    return sum(1 for p in us.glob("plane_*") if p.is_dir()) if us.is_dir() else 0


def case_source_levels(case_dir) -> tuple[str, ...]:
    """The source levels a case folder has data for (every feature file of the source in
    ``intraop/``): a study adds these rows to a case that has them, and only to it."""
    intraop = Path(case_dir) / "intraop"
    return tuple(f"S+{s}" for s in SOURCES
                 if all((intraop / f"{n}.csv").exists() for n in features_of(s)))


def plane_count(level: str) -> int:
    """n of "S+n"."""
    if not has_planes(level) or level == "S+all":
        raise ValueError(f"{level!r} is not S + a number of planes")
    return int(level[2:])


def fixed_planes(level: str, n_planes: int) -> tuple[int, ...]:
    """The planes of a level that names them all or none: every one of the case's
    ``n_planes`` for "S+all", none for "rigid", "S", a source level, "CBCT" and "iCT". "S+n" leaves the
    choice of n planes to the study (``ValueError``)."""
    if level == "S+all":
        return tuple(range(n_planes))
    if has_planes(level):
        raise ValueError(f"{level!r} names how many planes, not which")
    return ()


def stylus_only_pose(level: str) -> bool:
    """True for the levels whose rigid stage sees only the stylus data (``registration.rigid``
    fits the surface features, which are the stylus's for S and every S + planes), so one
    rigid ICP serves all of a case's S and S + planes rows. A source level is not one: a
    source's liver-surface points steer the rigid ICP too (``features.RIGID``)."""
    return level == "S" or has_planes(level)


def study_data(case_dir, level: str, planes=(), case=None, stylus=None) -> dict:
    """The data of a study level (``LEVELS``): "rigid" and "S" the stylus data (``stylus``
    when given, for a caller that reads it once per case), "S+n" and "S+all" S and
    ``planes``, a source level S and the source's points, "CBCT" and "iCT" the full surfaces."""
    if level in ("rigid", "S"):
        return data_level(case_dir, "S", case=case) if stylus is None else stylus
    if source_of(level) is not None and stylus is not None:
        return {**stylus, **data_level(case_dir, level, case=case, only_source=True)}
    if has_planes(level):
        return data_level(case_dir, "S+planes", planes=planes, case=case)
    return data_level(case_dir, level, case=case)


def data_level(case_dir, level: str, planes=(), spacing=3.0, case=None, only_source=False) -> dict:
    """Intraoperative data (feature → (N, 3) mm) of ``level`` for a simulated case;
    ``only_source``: of a source level, the source's points without S."""

    case_dir = Path(case_dir)
    case = case or read_case(case_dir)
    if level == "S":
        return {k: v for k, v in case.intraop.items() if k in STYLUS}
    source = source_of(level)
    if source is not None:
        missing = [n for n in features_of(source) if n not in case.intraop]
        if missing:
            raise InputError(f"no {source} points in this case (intraop/{missing[0]}.csv)", case_dir / "intraop")
        out = {} if only_source else data_level(case_dir, "S", case=case)
        return out | {n: case.intraop[n] for n in features_of(source)}
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
    raise InputError(f"unknown data level {level!r} (S, S+planes, {', '.join(SOURCE_LEVELS + ('CBCT', 'iCT'))})")
