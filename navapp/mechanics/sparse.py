"""Sparse symmetric positive-definite factorisation with a fast back end where available.

MKL PARDISO (via pypardiso, a pip wheel on x86_64) factorises the paper-scale liver
(≈57k DOFs) in about a second; SciPy's SuperLU is the portable fallback (same answers,
minutes instead of seconds at that size). ``NAVAPP_SOLVER=superlu`` forces the fallback.

SuperLU is given METIS's nested-dissection ordering of the matrix's node graph (``nested_dissection``)
rather than its own minimum degree: on the 4 mm liver held at its supports (52k DOFs) the factor
holds 52 M entries instead of 77 M, and the factorisation and solves take 4× and 2× less time,
with the same answers to 10⁻¹³ (docs/decisions/local-loads.md).
"""

import ctypes
import glob
import os
import sys
from contextlib import contextmanager

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


def backend() -> str:
    if os.environ.get("NAVAPP_SOLVER", "").lower() == "superlu":
        return "superlu"
    _name_mkl_rt()
    try:
        import pypardiso  # noqa: F401
    except ImportError:
        return "superlu"
    return "pardiso"


def mkl_rt_path() -> str | None:
    """Where the installed ``mkl`` wheel put libmkl_rt, or None.

    pypardiso looks for it only under ``sys.prefix`` and fails at import when it is not
    there. In a virtual environment made with ``--system-site-packages``, or with MKL
    installed by ``pip install --user``, the library lies outside ``sys.prefix``: pypardiso
    then did not import and every factorisation fell back to SuperLU (the 4 mm liver's
    point-load modes 7 CPU s → 50+, the demo's truth solve minutes). The wheel's own file
    list says where it is, wherever pip installed it."""
    from importlib import metadata

    try:
        dist = metadata.distribution("mkl")
    except metadata.PackageNotFoundError:
        dist = None
    found = []
    if dist is not None:
        for f in dist.files or ():
            if f.name.startswith(("libmkl_rt.", "mkl_rt.")) and not f.name.endswith(".lib"):
                path = str(dist.locate_file(f))
                if os.path.exists(path):
                    found.append(path)
    for prefix in (sys.prefix, sys.base_prefix):  # a wheel without a file list (RECORD)
        found += glob.glob(os.path.join(prefix, "lib", "libmkl_rt.so*"))
    return min(found, key=len) if found else None


def _name_mkl_rt():
    """Name libmkl_rt to pypardiso through its environment variable, unless already named:
    without it pypardiso walks the whole of ``sys.prefix`` for it on every solver it creates
    (about a second here, once per tile of the relaxation), and finds nothing outside it."""
    if "PYPARDISO_MKL_RT" not in os.environ:
        path = mkl_rt_path()
        if path is not None:
            os.environ["PYPARDISO_MKL_RT"] = path


def _pardiso_solver():
    """A new PyPardisoSolver for a real SPD matrix (libmkl_rt named to it first)."""
    _name_mkl_rt()
    import pypardiso

    s = pypardiso.PyPardisoSolver(mtype=2)  # real symmetric positive definite
    os.environ.setdefault("PYPARDISO_MKL_RT", s.libmkl._name)
    return s


@contextmanager
def one_mkl_thread():
    """MKL (hence PARDISO) on one thread in the calling thread only, within it
    (``mkl_set_num_threads_local``), for factorisations run side by side in a pool: two of MKL's
    two-thread teams on two cores would only wait on each other, and one thread gives the same
    bits each run (two gave results differing by 2–3e-15 between runs: docs/decisions/speed.md,
    session 32). Nothing where PARDISO is not the back end."""
    if backend() != "pardiso":
        yield
        return
    # the C entry point (the lower-case symbol is the Fortran one, which takes a pointer)
    set_local = _pardiso_solver().libmkl.MKL_Set_Num_Threads_Local
    previous = set_local(ctypes.c_int(1))
    try:
        yield
    finally:
        set_local(ctypes.c_int(previous))  # 0: the process-wide setting again


PARDISO_OUT_OF_MEMORY = (-2, -9)  # MKL PARDISO's codes: not enough memory; not enough for out-of-core


def _pardiso(solver, A, B):
    """One PARDISO call; its out-of-memory codes become ``MemoryError``, which the command
    line says in one line (a basis at k = 1000 on a 4 mm liver ended in "error code -2")."""
    try:
        return solver._call_pardiso(A, B)
    except Exception as exc:
        from pypardiso.pardiso_wrapper import PyPardisoError  # here, not on every solve

        if isinstance(exc, PyPardisoError) and exc.value in PARDISO_OUT_OF_MEMORY:
            raise MemoryError(f"PARDISO ran out of memory (code {exc.value})") from None
        raise


def nested_dissection(A: sp.csr_matrix) -> np.ndarray | None:
    """A fill-reducing permutation (n,) of a symmetric matrix, METIS's nested dissection (pymetis)
    of its graph: of the node graph when the unknowns come in node triples whose 3 × 3 blocks
    make the whole pattern (a finite-element stiffness), each node's three kept together;
    else of the unknowns' own graph. None where pymetis is not installed (an environment made
    before it was a dependency): SuperLU's minimum degree then, slower, the same answers to rounding."""
    try:
        import pymetis
    except ImportError:
        return None

    n = A.shape[0]
    G = sp.csr_matrix((np.ones(A.nnz), A.indices, A.indptr), shape=A.shape)
    block = 3 if n % 3 == 0 and n > 3 else 1
    if block == 3:
        S = sp.kron(sp.identity(n // 3, format="csr"), np.ones((1, 3)), format="csr")  # (n/3, n): sums a triple
        N = (S @ G @ S.T).tocsr()
        if sp.kron(N, np.ones((3, 3))).nnz != G.nnz:  # some triple is not a node's: no compression
            block, N = 1, G
    else:
        N = G
    N = N.tolil()
    N.setdiag(0)
    N = N.tocsr()
    N.eliminate_zeros()
    xadj, adjncy = N.indptr.astype(np.int64), N.indices.astype(np.int64)
    if hasattr(pymetis, "CSRAdjacency"):  # pymetis ≥ 2025.2 (its xadj/adjncy keywords are deprecated)
        order = pymetis.nested_dissection(adjacency=pymetis.CSRAdjacency(xadj, adjncy))
    else:
        order = pymetis.nested_dissection(xadj=xadj, adjncy=adjncy)
    perm = np.asarray(order[0], dtype=np.int64)
    return (block * perm[:, None] + np.arange(block)).ravel()


def upper_triangle(A: sp.csr_matrix) -> sp.csr_matrix:
    """The upper triangle (diagonal included) of a CSR matrix, its column indices sorted:
    what PARDISO takes of a symmetric matrix. A mask on the stored entries (SciPy's ``triu``
    goes through COO and back: 0.76 of the relaxation's 3 CPU s, 45 tiles at 22k nodes)."""
    if not A.has_sorted_indices:
        A = A.sorted_indices()
    rows = np.repeat(np.arange(A.shape[0], dtype=A.indices.dtype), np.diff(A.indptr))
    keep = A.indices >= rows
    indptr = np.zeros(A.shape[0] + 1, A.indptr.dtype)
    np.cumsum(np.bincount(rows[keep], minlength=A.shape[0]), out=indptr[1:])
    return sp.csr_matrix((A.data[keep], A.indices[keep], indptr), shape=A.shape)


class Factorisation:
    """A factorised SPD matrix A; ``solve(B)`` takes (n,) or (n, r) right-hand sides."""

    def __init__(self, A: sp.spmatrix):
        A = sp.csr_matrix(A)
        self.n = A.shape[0]
        self.kind = backend()
        if self.kind == "pardiso":
            self._A = upper_triangle(A)
            self._s = _pardiso_solver()
            # MKL's defaults for a real SPD matrix, but for one: the factor kept in variable
            # blocks (VBSR, iparm[36] < 0), which suits FE DOFs that come in node triples.
            # Measured at 27k nodes: the 135 solves of the point-load modes 5.0 → 2.0 s,
            # factorisation unchanged, answers equal to 1e-14.
            p = self._s.iparm
            p[0] = 1  # parameters given here, not all defaults
            p[1] = 2  # METIS nested dissection
            p[9] = 8  # pivot perturbation 1e-8
            p[36] = -80  # VBSR: merge supernode columns whose patterns agree to 80 %
            self._s.set_phase(12)
            try:
                _pardiso(self._s, self._A, np.zeros((self.n, 1)))
            except BaseException:
                # a refused factorisation (not positive definite: the neo-Hookean truth's
                # shifted retries) still holds PARDISO's work memory, and no ``with`` frees it:
                # a simulation grew past 24 GB this way and was killed by the kernel
                self._s.free_memory(everything=True)
                raise
            self._s.factorized_A = self._A
        else:
            p = nested_dissection(A)
            self._p = np.arange(self.n) if p is None else p
            # the ordering is the factor's (NATURAL); SuperLU's own threshold pivoting stays, so an
            # indefinite matrix (the neo-Hookean truth's Newton steps) is factorised as before — on
            # the SPD stiffness it took every diagonal pivot (the same 52 M entries with or without)
            self._lu = spla.splu(A[self._p][:, self._p].tocsc(), permc_spec="MMD_AT_PLUS_A" if p is None else "NATURAL",
                                 options={"SymmetricMode": True})

    def solve(self, B: np.ndarray) -> np.ndarray:
        B = np.asarray(B, float)
        if self.kind == "pardiso":
            self._s.set_phase(33)
            X = _pardiso(self._s, self._A, np.asfortranarray(B.reshape(self.n, -1)))
            return X.reshape(B.shape)
        X = np.empty_like(B)
        X[self._p] = self._lu.solve(np.ascontiguousarray(B[self._p]))
        return X

    def free(self):
        if self.kind == "pardiso":
            self._s.free_memory(everything=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.free()
