"""Local modes where the data say the surface moved, kept only where held-out data gain.

A tool dent of 1–5 cm is not in the span of the control-point basis (``mechanics.local_modes``).
After the first fit, the liver-surface data it leaves more than ``off_mm`` off its surface
mark where the surface moved in a way the basis cannot make. Under up to ``max_sources``
k-means centres of those points, ``depth_mm`` inside the fitted surface, a Kelvin point-load
source adds three modes; the strain energy of eq. 13 is extended over them and the model is
fitted again.

More modes always fit the data better, so the data the fit saw cannot say whether they help.
The same spatial blocks as the cross-validation (``support.blocks_of``) can: per block,
today's basis and the extended one (sources placed from the *training* blocks' own fit, so
no held-out point has a say where its modes go) are fitted to the other blocks and predict
the held-out one. The modes are kept where the held-out RMS drops by more than ``min_gain``
(relative). The truth is never read. docs/decisions/local-loads.md ("Local modes in
register") has the measurements; the constants were set before the probe's first run.
"""

import time
from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.cluster.vq import kmeans2

from ..features import SALIENT
from ..mechanics.fem import nodal_strain_operator
from ..mechanics.local_modes import EPS_MM, MODE_MM, kelvin_modes, with_modes
from .libr import LMOptions
from .model import DATA_TO_MODEL, RegistrationModel, deform, extended_model
from .support import Support, SupportOptions, check_support_pair


@dataclass(frozen=True)
class LocalModeOptions:
    """Where local modes go and when a fit keeps them (module doc)."""

    off_mm: float = 2.5  # a surface data point farther than this from the fitted surface is unexplained
    min_points: int = 8  # fewer unexplained points: no modes
    per_source: int = 40  # one source per this many unexplained points ...
    max_sources: int = 2  # ... and at most this many
    depth_mm: float = 10.0  # a source lies this far inside the surface node nearest its centre
    eps_mm: float = EPS_MM
    scale_mm: float = MODE_MM
    min_gain: float = 0.05  # the held-out RMS must drop by more than this (relative) for the modes to be kept


@dataclass
class LocalModes:
    """What the local-mode step did: the surface nodes its sources lie under (model
    frame, from all the data), the held-out RMS with today's basis and with the extended one
    (mm, point-weighted mean over the blocks; None where there were too few data to
    split), and whether the answer uses them."""

    nodes: list[int] = field(default_factory=list)
    heldout_base_mm: float | None = None
    heldout_extended_mm: float | None = None
    adopted: bool = False
    seconds: float = 0.0

    def as_dict(self) -> dict:
        def mm(v):
            return None if v is None else round(v, 3)

        return {"sources": len(self.nodes), "source_nodes": [int(i) for i in self.nodes],
                "heldout_base_mm": mm(self.heldout_base_mm), "heldout_extended_mm": mm(self.heldout_extended_mm),
                "adopted": self.adopted, "seconds": round(self.seconds, 3)}


def surface_data(data: dict) -> np.ndarray:
    """The points of the features that slide on the liver surface or its regions, (N, 3) mm."""
    pts = [p for k, p in data.items() if DATA_TO_MODEL[k] in ("liver", *SALIENT)]
    return np.vstack(pts) if pts else np.zeros((0, 3))


def place_sources(model: RegistrationModel, beta: np.ndarray, data: dict,
                  opts: LocalModeOptions = LocalModeOptions()) -> tuple[np.ndarray, np.ndarray]:
    """Where the fit ``beta`` (3k + 6,) leaves the surface data (feature → (N, 3) mm, model
    frame) more than ``opts.off_mm`` off: ``sources_under`` the fitted mesh."""
    b = model.basis
    n = len(beta) - 6
    _, x = deform(b.nodes, (b.Ju @ beta[:n]).reshape(-1, 3), beta, model.centroid)
    return sources_under(model, x, surface_data(data), opts)


def sources_under(model: RegistrationModel, x: np.ndarray, pts: np.ndarray,
                  opts: LocalModeOptions = LocalModeOptions()) -> tuple[np.ndarray, np.ndarray]:
    """The surface nodes (s,) int the sources lie under, and the sources (s, 3) mm in the
    undeformed mesh, for the points ``pts`` (N, 3) mm farther than ``opts.off_mm`` from the
    fitted surface whose nodes are at ``x`` (M, 3) mm in the same frame (any rigid frame:
    the placement moves with it). Both empty where too few points are off."""
    b = model.basis
    none = np.zeros(0, int), np.zeros((0, 3))
    if len(pts) < opts.min_points:
        return none
    _, dist, _ = trimesh.proximity.closest_point(trimesh.Trimesh(x, b.surface_faces, process=False), pts)
    off = pts[dist > opts.off_mm]
    if len(off) < opts.min_points:
        return none
    count = min(opts.max_sources, max(1, len(off) // opts.per_source))
    centres = kmeans2(off, count, seed=0, minit="++")[0] if count > 1 else off.mean(0, keepdims=True)
    normals = trimesh.Trimesh(b.nodes, b.surface_faces, process=False).vertex_normals  # outward, undeformed
    # two centres nearest one node would give one source twice (identical modes)
    nodes = np.unique([b.surface[np.argmin(np.linalg.norm(x[b.surface] - c, axis=1))] for c in centres])
    return nodes, b.nodes[nodes] - opts.depth_mm * normals[nodes]


def with_sources(model: RegistrationModel, nodes: np.ndarray, sources: np.ndarray,
                 opts: LocalModeOptions = LocalModeOptions()) -> RegistrationModel:
    """``model`` with three Kelvin modes per source (s, 3) mm appended (``mechanics.local_modes``)."""
    b = model.basis
    if model.cache.strain_operator is None:  # the same mesh in every fold and registration (≈ 28 MB at 18.5k nodes)
        model.cache.strain_operator = nodal_strain_operator(b.nodes, b.tets)
    cols = np.hstack([kelvin_modes(b.nodes, s, b.material.nu, opts.eps_mm, opts.scale_mm) for s in sources])
    return extended_model(model, with_modes(b, cols, nodes, model.cache.strain_operator))


def choose_local_modes(model: RegistrationModel, data: dict, beta: np.ndarray, options: LMOptions,
                       settings: SupportOptions | None = None, opts: LocalModeOptions = LocalModeOptions(),
                       cancel=None) -> tuple[RegistrationModel | None, LocalModes | None, Support | None]:
    """The extended model if held-out data say the fit should keep local modes (module doc).

    Parameters
    ----------
    model : RegistrationModel
    data : dict
        feature → (N, 3) mm in the model frame (after the rigid pose).
    beta : (3k + 6,)
        the fit to all of ``data`` with today's basis: where the sources go.
    options : LMOptions
        the real fit's settings (a kept pose stays kept in the folds).
    settings : SupportOptions, optional
        the blocks, the LM cap per fold and the fewest points to split (default ``SupportOptions()``).

    Returns
    -------
    model : RegistrationModel or None
        the extended model where its modes are kept, else None.
    report : LocalModes or None
        None only when cancelled.
    support : Support or None
        the cross-validation of the answer's basis against the rigid answer, from the same
        folds (``support.check_support_pair``): the extended basis' with each fold's own
        sources, or today's (then equal to ``check_support``'s); None where there was no
        cross-validation (no modes to weigh, too few data, cancelled).
    """
    t0 = time.perf_counter()
    settings = SupportOptions() if settings is None else settings
    nodes, sources = place_sources(model, beta, data, opts)
    report = LocalModes(nodes=nodes.tolist())
    pair = None
    if len(nodes):
        pair = check_support_pair(model, data, options, settings, cancel, extend=lambda train, b: fold_model(
            model, train, b, opts))
        if cancel is not None and cancel.is_set():
            return None, None, None
    report.seconds = time.perf_counter() - t0
    if pair is None:
        return None, report, None
    base, ext = pair
    report.heldout_base_mm, report.heldout_extended_mm = base.deformable_mm, ext.deformable_mm
    report.adopted = ext.deformable_mm < (1 - opts.min_gain) * base.deformable_mm
    if not report.adopted:
        return None, report, base
    return with_sources(model, nodes, sources, opts), report, ext


def fold_model(model: RegistrationModel, train: dict, beta: np.ndarray,
               opts: LocalModeOptions = LocalModeOptions()) -> RegistrationModel | None:
    """``model`` extended under the training data its fit ``beta`` leaves off, or None."""
    nodes, sources = place_sources(model, beta, train, opts)
    return with_sources(model, nodes, sources, opts) if len(nodes) else None
