"""Tracked intraoperative ultrasound: the scene's preset planes, and one frame at a pose the
user or the tracker chose (a free plane, a live frame's automatic segmentation).

The iUS planes are in every scene (``[ius]`` optional, 16 planes otherwise) and draw on the
scene's own random stream after the stylus, as they did before sources were rooms: a scene
simulates to the same files as then. A tracked frame applies the scene's acquisition effects
itself (``acquires_effects``): a tracking error moves the frame's pixels through its pose, a
dropout its segmented points; the section geometry and the B-mode image are
``simulation/ultrasound.py``. Its frames are written under ``intraop/us`` (``write_frames``)
and read back by the viewer (``read_frames``).

In a scene::

    [ius]
    planes = 16              # 8 vertical + 8 lateral; 0 for none
"""

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ... import progress
from ...anatomy.caseio import read_csv, write_csv
from ...defaults import N_PLANES
from ...errors import InputError
from ..effects import Effect
from ..probe import Probe
from ..ultrasound import PlaneData, acquire_plane, plane_poses
from . import Acquired, Sight, SimulatedSource

NAME = "ius"


@dataclass(frozen=True)
class IusSpec:
    """A scene's ``[ius]``. The field name is the scene's own field's, so a scene's cache and
    session keys are as before (``scenedata._scene_params``)."""

    planes: int = N_PLANES


def parse(table, path) -> IusSpec:
    """A scene's ``[ius]`` table; one ``InputError`` line for anything wrong (the messages the
    scene parser gave)."""
    if not isinstance(table, dict):
        raise InputError("[ius] must be a table", path)
    for key, value in table.items():
        if key != "planes":
            raise InputError(f"unknown key ius.{key} (known: planes)", path)
        if not isinstance(value, int) or isinstance(value, bool):
            raise InputError(f"ius.planes must be a int, got {value!r}", path)
    spec = IusSpec(**table)
    if not 0 <= spec.planes <= N_PLANES:
        raise InputError(f"ius.planes must be between 0 and {N_PLANES}", path)
    return spec


def acquire(spec: IusSpec, sight: Sight, rng: np.random.Generator) -> Acquired:
    """The preset planes (half vertical, half lateral, on the deformed anterior surface), their
    features merged per feature in plane order, and each plane's point counts (the report's
    ``planes``)."""
    probe = Probe()
    frames: list[PlaneData] = []
    if spec.planes:
        liver = sight.liver
        poses = plane_poses(liver.vertices, liver.vertex_normals, sight.preop.region_mask("anterior"), spec.planes,
                            sight.seed)
        with progress.bar(len(poses), "iUS planes", "plane") as pb:
            for i, (orientation, T) in enumerate(poses):
                frames.append(acquire_plane(i, orientation, T, probe, liver, sight.vessels.get("portal"),
                                            sight.vessels.get("hepatic"), sight.effects, rng, sight.ledger,
                                            want_image=True))
                pb.update(1)
    points: dict[str, np.ndarray] = {}
    for pl in frames:
        for k, pts in pl.features.items():
            points[k] = np.vstack([points[k], pts]) if k in points else pts
    return Acquired(points, [{k: int(len(p)) for k, p in pl.features.items()} for pl in frames], frames)


def frame(spec: IusSpec, sight: Sight, index: int, probe_to_tracker: np.ndarray, live: bool) -> PlaneData:
    """One frame at ``probe_to_tracker`` (4 × 4, mm) on the deformed anatomy, on a stream of
    its own (the scene's seed and ``index``), so that it is reproducible.

    ``live=False``: a free plane the user placed, with its B-mode image and the scene's
    effects as for a preset. ``live=True``: the features an automatic segmentation
    designates on a live frame (the image is the tracker's own): its contours perturbed by
    the scene's declared ``auto_segmentation`` error in place of any ``contour_jitter``,
    the other effects as for any plane; no features when the scene declares none.
    """
    T = np.asarray(probe_to_tracker, float)
    vessels = sight.vessels.get("portal"), sight.vessels.get("hepatic")
    if not live:
        rng = np.random.default_rng([sight.seed, index])
        return acquire_plane(index, "free", T, Probe(), sight.liver, *vessels, sight.effects, rng, sight.ledger,
                             want_image=True)
    sd_px = auto_segmentation(sight.effects)
    if sd_px is None:
        return PlaneData(index, "live", T, {})
    effects = [e for e in sight.effects if e.kind not in ("contour_jitter", "auto_segmentation")]
    if sd_px > 0:
        effects.append(Effect("contour_jitter", {"sd_px": sd_px}))
    rng = np.random.default_rng([sight.seed, 7, index])
    return acquire_plane(index, "live", T, Probe(), sight.liver, *vessels, effects, rng, sight.ledger,
                         want_image=False)


def auto_segmentation(effects) -> float | None:
    """The contour error (px) of the scene's declared automatic segmentation of live frames,
    or None when it declares none (then live frames carry no features until the user draws
    on a frozen one)."""
    for e in effects:
        if e.kind == "auto_segmentation":
            return float(e.params["sd_px"])
    return None


def write_frames(folder, frames: list[PlaneData], probe: Probe | None = None):
    """``intraop/us/planes.json`` (per plane its index, orientation, true ProbeToTracker pose
    and feature files; the probe's calibration), each plane's features
    (``plane_XX/<feature>.csv``) and B-mode image (``plane_XX.png``). Nothing without frames."""
    if not frames:
        return
    from skimage.io import imsave

    probe = probe or Probe()
    udir = Path(folder) / "intraop" / "us"
    udir.mkdir(parents=True, exist_ok=True)
    meta: dict = {"image_to_probe": probe.image_to_probe().tolist(), "width_px": probe.width_px,
                  "height_px": probe.height_px, "spacing_mm": probe.spacing_mm, "planes": []}
    for pl in frames:
        pdir = udir / f"plane_{pl.index:02d}"
        pdir.mkdir(exist_ok=True)
        for k, pts in pl.features.items():
            write_csv(pdir / f"{k}.csv", pts, ("x", "y", "z"))
        if pl.image is not None:
            imsave(udir / f"plane_{pl.index:02d}.png", pl.image, check_contrast=False)
        meta["planes"].append({"index": pl.index, "orientation": pl.orientation,
                               "probe_to_tracker": np.asarray(pl.probe_to_tracker).tolist(),
                               "features": sorted(pl.features)})
    (udir / "planes.json").write_text(json.dumps(meta, indent=1))


def read_frames(case_dir) -> tuple[list[PlaneData], Probe]:
    """The preset planes ``write_frames`` wrote: poses, features and images, and the probe."""
    from skimage.io import imread

    udir = Path(case_dir) / "intraop" / "us"
    meta_path = udir / "planes.json"
    if not meta_path.exists():
        return [], Probe()
    meta = json.loads(meta_path.read_text())
    probe = Probe(meta["width_px"], meta["height_px"], meta["spacing_mm"])
    planes = []
    for p in meta["planes"]:
        pdir = udir / f"plane_{p['index']:02d}"
        feats = {f: read_csv(pdir / f"{f}.csv", ("x", "y", "z")) for f in p["features"]}
        img_path = udir / f"plane_{p['index']:02d}.png"
        image = imread(img_path) if img_path.exists() else None
        planes.append(PlaneData(p["index"], p["orientation"], np.array(p["probe_to_tracker"]), feats, image))
    return planes, probe


SOURCE = SimulatedSource(NAME, always=True, parse=parse, acquire=acquire, acquires_effects=True, frame=frame,
                         report_key="planes")
