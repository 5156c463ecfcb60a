"""A basis computed with declared supports (``BasisSettings.supports``): every mode vanishes at
the held nodes, and it can make what a support-held organ does (a swing about its bare area)
where the free-floating basis cannot without moving the whole organ."""

import numpy as np
import pytest

from navapp.mechanics.basis import BasisSettings, basis_key, compute_basis
from navapp.mechanics.fem import Material
from navapp.mechanics.supports import REGIONS, held_nodes


@pytest.mark.parametrize("supports", [s.value for s in REGIONS])
def test_every_mode_vanishes_at_the_supports(coarse_mesh, supports):
    held = held_nodes(coarse_mesh, supports)
    assert len(held) > 0
    basis = compute_basis(coarse_mesh, BasisSettings(k=12, supports=supports))
    U = basis.Ju.reshape(basis.M, 3, -1)
    assert np.abs(U[held]).max() == 0.0  # held exactly, not approximately
    assert not np.isin(basis.control, held).any()
    assert np.all(np.linalg.eigvalsh(basis.energy) > 0)  # no mode is free of strain: no rigid motion left


def test_the_point_load_modes_move_their_control_point_and_hold_the_support(coarse_mesh):
    """Before relaxation, mode (c, d) moves control point c by the perturbation along d and
    every other control point and held node not at all."""
    basis = compute_basis(coarse_mesh, BasisSettings(k=12, supports="bare_area", relax=False))
    U = basis.Ju.reshape(basis.M, 3, -1)
    for c, node in enumerate(basis.control):
        assert np.allclose(U[node, :, 3 * c:3 * c + 3], 5.0 * np.eye(3), atol=1e-9)
    others = np.delete(basis.control, 0)
    assert np.abs(U[others, :, :3]).max() < 1e-9
    assert np.abs(U[held_nodes(coarse_mesh, "bare_area")]).max() == 0.0


def test_the_free_basis_keeps_its_cache_key(coarse_mesh):
    """Bases cached before supports existed stay valid: the key of a free basis has no supports entry."""
    free = basis_key(coarse_mesh, BasisSettings(k=12), Material())
    held = basis_key(coarse_mesh, BasisSettings(k=12, supports="bare_area"), Material())
    assert free != held
    assert free == basis_key(coarse_mesh, BasisSettings(k=12, supports=None, release="L"), Material())


def test_the_truths_supports_are_the_declared_ones(coarse_mesh):
    """One rule for both: the simulated truth holds exactly the nodes a declared support names."""
    from navapp.simulation.truth import supported_nodes

    for s in REGIONS:
        ours = held_nodes(coarse_mesh, s)
        theirs = np.unique(np.concatenate(list(supported_nodes(coarse_mesh, "N", s).values())))
        assert np.array_equal(ours, theirs)
