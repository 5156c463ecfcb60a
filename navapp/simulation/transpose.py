"""Transposed deformations, as the paper made its cases (§III-A).

The paper did not deform each liver with its own elastic model: it deformed one
reference liver (three laparoscopic mobilisations, L, N, R) and mapped those
displacement fields onto other liver geometries through an inexact correspondence,
affine then deformable. The mapped field is not an elastic equilibrium of the
target liver: the correspondence error leaves non-elastic distortions inside the
organ, which surface data cannot reveal but vessels can.

Here:

1. ``reference_deformation``: the reference liver's own force-driven truth (anterior
   pressure, gravity, L/N/R ligament release, neo-Hookean when ``large``);
   cached by content.
2. ``correspondence``: φ, target liver → reference liver. Coherent Point Drift
   (``pycpd``) on surface samples: affine, then deformable (Gaussian motion coherence);
   then a smoothing thin-plate spline from the target samples to their CPD images
   extends φ into the volume. Neither stage is exact (CPD is a soft, regularised
   match; the spline smooths), which is the point.
3. ``transpose``: the reference deformation ψ(X) = X + u(X) is split into its best
   rigid motion, X ↦ R X + b (least squares over the reference nodes), and the
   non-rigid residual r(X) = ψ(X) − (R X + b). The target point x goes to
   ``R x + b + Q r(φ(x))`` with Q the rotation of φ's affine stage (vectors carried
   back into the target's frame). So a rigid reference motion transposes to exactly
   that rigid motion and the identity to the identity, whatever φ; only the
   non-rigid part goes through the inexact correspondence.

Supported regions after transposition: the target's own bare area and ligaments are
not re-clamped. They move as the transposed field says (near zero where φ lands on
the reference's supports, not exactly zero elsewhere); ``simulate`` reports that
motion (``report.json``: ``transposed.support_displacement_mm``). See
docs/decisions/mechanics.md.
"""

from dataclasses import asdict, dataclass

import numpy as np
from scipy.interpolate import RBFInterpolator

from .. import cache
from ..anatomy.meshing import TetMesh, cached_tetmesh
from ..geometry.interpolation import barycentric
from ..geometry.transforms import apply_rigid, homogeneous, kabsch
from ..threads import limit_threads
from .truth import solve_linear, solve_neo_hookean

CPD_POINTS = 700  # surface samples per liver for CPD (O(N²) per iteration)
CPD_BETA_MM = 40.0  # width of CPD's Gaussian motion-coherence kernel
CPD_ALPHA = 2.0  # CPD's smoothness weight
TPS_SMOOTHING = 10.0  # thin-plate smoothing (mm² scale): φ does not interpolate CPD exactly
LOAD_STEPS = 4  # first Newton load increment of the large-deformation reference: 1/4 of the load (adaptive after)


@dataclass(frozen=True)
class Correspondence:
    """φ: target liver → reference liver (mm).

    Attributes
    ----------
    affine : (4, 4) the affine stage, target → reference (homogeneous, column vectors)
    rotation : (3, 3) the rotation of the affine stage's linear part (polar decomposition)
    spline : thin-plate spline, target points (N, 3) → reference points (N, 3)
    residual_mm : RMS distance from the mapped target samples to the reference surface samples' nearest points
    """

    affine: np.ndarray
    rotation: np.ndarray
    spline: RBFInterpolator
    residual_mm: float

    def __call__(self, points) -> np.ndarray:
        return self.spline(np.atleast_2d(np.asarray(points, float)))


def _samples(vertices, n, rng):
    vertices = np.asarray(vertices, float)
    if len(vertices) <= n:
        return vertices.copy()
    return vertices[np.sort(rng.choice(len(vertices), n, replace=False))]


def correspondence(target_vertices, reference_vertices, n_points=CPD_POINTS, beta=CPD_BETA_MM, alpha=CPD_ALPHA,
                   smoothing=TPS_SMOOTHING, seed=0) -> Correspondence:
    """Affine, then deformable CPD of the target surface onto the reference surface,
    extended into the volume by a smoothing thin-plate spline.

    Parameters
    ----------
    target_vertices, reference_vertices : (V, 3) mm, surface points of each liver
    n_points : samples per surface given to CPD
    beta, alpha : CPD's coherence kernel width (mm) and smoothness weight
    smoothing : the spline's smoothing (0: interpolate the CPD matches exactly)
    """
    from pycpd import AffineRegistration, DeformableRegistration
    from scipy.spatial import cKDTree


    rng = np.random.default_rng(seed)
    y = _samples(target_vertices, n_points, rng)
    x = _samples(reference_vertices, n_points, rng)
    # one BLAS thread: pycpd solves an N × N system per iteration, and on this shared 2-core
    # machine the threaded solve was 7× slower (36.5 s against 4.9 s for 300 points, under load)
    with limit_threads(1):
        # pycpd: X fixed, Y moving; TY = Y B + t (row vectors)
        ya, (B, t) = AffineRegistration(X=x, Y=y, max_iterations=100, tolerance=1e-6).register()
        yd, _ = DeformableRegistration(X=x, Y=ya, alpha=alpha, beta=beta, max_iterations=150,
                                       tolerance=1e-6).register()
    A = homogeneous(B.T, t)
    u, _, vt = np.linalg.svd(B.T)
    Q = u @ vt
    if np.linalg.det(Q) < 0:
        u[:, -1] *= -1
        Q = u @ vt
    spline = RBFInterpolator(y, yd, kernel="thin_plate_spline", smoothing=smoothing, degree=1)
    res = float(np.sqrt(np.mean(cKDTree(np.asarray(reference_vertices, float)).query(spline(y))[0] ** 2)))
    return Correspondence(A, Q, spline, res)


def sample_field(mesh: TetMesh, field, points) -> np.ndarray:
    """A nodal field (M, 3) at ``points`` (P, 3): barycentric inside the mesh; outside,
    the nearest tet's weights clipped to [0, 1] and renormalised (bounded, never
    extrapolated: φ may land a few mm outside the reference liver)."""
    tet, w = barycentric(mesh.nodes, mesh.tets, points)
    w = np.clip(w, 0.0, None)
    w /= w.sum(1, keepdims=True)
    return np.einsum("pa,pai->pi", w, np.asarray(field)[mesh.tets[tet]])


def transpose(reference: TetMesh, u_ref, phi: Correspondence, points) -> np.ndarray:
    """Displacement (P, 3) mm at target ``points`` (P, 3) of the reference deformation
    ``u_ref`` (M, 3) on ``reference``, carried through φ (module doc): x ↦ R x + b + Q r(φ(x))."""
    X = reference.nodes
    R, b = kabsch(X, X + u_ref)
    residual = X + u_ref - apply_rigid(R, b, X)
    points = np.asarray(points, float)
    r = sample_field(reference, residual, phi(points)) @ phi.rotation  # Qᵀ: reference frame → target frame
    return apply_rigid(R, b, points) + r - points


def reference_deformation(reference_surface, mesh_edge_mm: float, loading, material, large: bool,
                          cache_root=None) -> tuple[TetMesh, np.ndarray]:
    """The reference liver's own truth: its tet mesh and nodal displacements (M, 3) mm
    under ``loading`` (``truth.Loading``: gravity, anterior pressure, release), linear or
    neo-Hookean (``large``). Cached by content (surface, mesh, loads, material, model)."""


    mesh, _ = cached_tetmesh(reference_surface, mesh_edge_mm, cache_root)
    root = cache.cache_dir() if cache_root is None else cache_root
    # the linear entry keeps its old key; the neo-Hookean one has its own tag (no SVK entry was ever saved)
    key = cache.content_key("reference-deformation-nh-1" if large else "reference-deformation-1", mesh.nodes,
                            mesh.tets, asdict(loading), {"E": material.E, "nu": material.nu}, bool(large))
    path = root / f"refdef-{key}.npz"
    hit = cache.load(path)
    if hit is not None:
        return mesh, hit["u"]
    u = (solve_neo_hookean(mesh, loading, material, steps=LOAD_STEPS) if large
         else solve_linear(mesh, loading, material))
    cache.save(path, {"u": u})
    return mesh, u
