"""poisson-cut's and laplace-beltrami-cut's P2 systems on the slabs of a structured box without MPI (docs/math.md §19): each
rank's pieces, on its cuts lifted by the Theta_h of its slab one layer wider, added up by the keys
of their P2 unknowns equal the serial order-2 matrix and load; the shifts of the owned nodes are the
serial ones; an unstructured mesh refuses order 2 on several ranks."""

import numpy as np
import pytest
import scipy.sparse as sp

from cutfem.distributed.partition import P2_SLOTS, partition_for, rank_cuts, slab_partition
from cutfem.distributed.laplace_beltrami import laplace_beltrami_pieces
from cutfem.distributed.poisson import poisson_pieces
from cutfem.fem.forms import assemble
from cutfem.fem.spaces import CutSpace
from cutfem.fem.terms import (face_jump_penalty, load, mass, nitsche, normal_gradient_penalty, stiffness,
                              tangential_stiffness)
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import CUT, NEG
from cutfem.problems.common import background_for, levelset_for
from cutfem.problems.laplace_beltrami import manufactured
from cutfem.problems.poisson import exact_u, source


@pytest.fixture(scope="module")
def sphere_p2():
    """The serial order-2 poisson-cut system of the unit sphere at spacing 0.2 (11 cell layers), as
    problems/poisson.py assembles it (gamma 10 k^2, gamma_g 0.01), and the keys of its unknowns
    written here: 8 v for the node v, 8 v + sum_i 2^i (ijk_i(w) - ijk_i(v)) for the edge {v, w}, v < w."""
    phi = levelset_for("sphere")
    bg = background_for(phi, 0.2, "structured", None)
    cut = cut_mesh(bg, phi, order=2)
    V = CutSpace(cut, NEG, order=2)
    dx = cut.dx(NEG)
    N = nitsche(cut.ds(), 40.0, g=exact_u)
    G = cut.ghost_facets(NEG)
    K = assemble(stiffness(dx) + N + 0.01 * face_jump_penalty(cut.dF(G), h_power=1), V)
    b = assemble(load(source, dx, degree=2) + N.load, V)
    return phi, bg, cut, V, K, b, G.n_facets, p2_keys(bg, V)


def p2_keys(bg, V):
    lo, hi = V.node_ids[V.edge_nodes[:, 0]], V.node_ids[V.edge_nodes[:, 1]]
    return np.concatenate([8 * V.node_ids, 8 * lo + (bg.node_index(hi) - bg.node_index(lo)) @ np.array([1, 2, 4])])


def summed(phi, bg, V, keys, counts, pieces):
    """The pieces of every rank of the partition ``counts``, added in the serial numbering."""
    assert P2_SLOTS == 8 and len(np.unique(keys)) == V.n_dofs
    order = np.argsort(keys)
    slabs = slab_partition(bg, len(counts), counts)
    n = V.n_dofs
    Ks, bs, faces = sp.csr_matrix((n, n)), np.zeros(n), 0
    for rank in range(len(counts)):
        parts = pieces(rank_cuts(slabs, rank, phi, order=2))
        faces += parts.faces
        for piece in parts.pieces:
            dofs = order[np.searchsorted(keys, piece.keys, sorter=order)]
            assert np.array_equal(keys[dofs], piece.keys)  # every row is a serial unknown
            c = piece.matrix.tocoo()
            Ks = Ks + sp.csr_matrix((c.data, (dofs[c.row], dofs[c.col])), shape=(n, n))
            if piece.vector is not None:
                np.add.at(bs, dofs, piece.vector)
    return Ks, bs, faces


@pytest.mark.parametrize("counts", [[11], [6, 5], [0, 5, 0, 6], [4, 1, 1, 5], [1] * 11])
def test_p2_pieces_add_up_to_the_serial_system(sphere_p2, counts):
    """[0, 5, 0, 6]: ranks without layers; [4, 1, 1, 5] and [1] * 11: one-layer slabs, whose nodes
    above and below have cut tets on the next ranks (seen through the wider lifting slab)."""
    phi, bg, _, V, K, b, n_faces, keys = sphere_p2
    Ks, bs, faces = summed(phi, bg, V, keys, counts, lambda cuts: poisson_pieces(cuts, 10.0, 0.01, order=2))
    x = np.random.default_rng(1).standard_normal(V.n_dofs)
    assert np.linalg.norm(Ks @ x - K @ x) <= 1e-13 * np.linalg.norm(K @ x)
    assert np.linalg.norm(bs - b) <= 1e-13 * np.linalg.norm(b)
    assert faces == n_faces  # each ghost face once


@pytest.mark.parametrize("stabilization", ["normal", "face"])
def test_laplace_beltrami_p2_pieces_add_up_to_the_serial_system(sphere_p2, stabilization):
    """P2 TraceFEM on the lifted S_h: the tangential stiffness, mass and load by the owner of each
    piece, the normal-gradient term (the order-2 default) on the owned cut tets, or J_F on every
    interior face of the cut tets once."""
    phi, bg, cut, *_ = sphere_p2
    sol = manufactured(phi)
    V = CutSpace(cut, CUT, order=2)
    dS = cut.ds()
    F = cut.interior_facets(CUT)
    stab = normal_gradient_penalty(cut.dx(CUT), h_power=-1.0) if stabilization == "normal" else \
        face_jump_penalty(cut.dF(F), h_power=1.0)
    K = assemble(tangential_stiffness(dS) + mass(dS) + stab, V)
    b = assemble(load(sol.f, dS, degree=4), V)
    Ks, bs, faces = summed(phi, bg, V, p2_keys(bg, V), [3, 0, 4, 1, 3],
                           lambda cuts: laplace_beltrami_pieces(cuts, sol, stabilization, 1.0, 1.0, 1.0, -1.0, order=2))
    x = np.random.default_rng(2).standard_normal(V.n_dofs)
    assert np.linalg.norm(Ks @ x - K @ x) <= 1e-13 * np.linalg.norm(K @ x)
    assert np.linalg.norm(bs - b) <= 1e-13 * np.linalg.norm(b)
    assert faces == (F.n_facets if stabilization == "face" else 0)


def test_owned_shifts_are_the_serial_ones(sphere_p2):
    """The shifts of the P2 nodes of each rank's owned slab (from its slab one layer wider) equal
    the serial Theta_h's at the same nodes; with the owned slab alone, a node on the slab's top
    plane would miss the cut tets above it."""
    phi, bg, cut, *_ = sphere_p2
    serial = cut.deformation
    slabs = slab_partition(bg, 3, [4, 3, 4])
    for rank in range(3):
        owned = rank_cuts(slabs, rank, phi, order=2).owned
        theta, n = owned.deformation, owned.background.n_points
        glob = owned.background.global_nodes(theta.node_keys // n) * bg.n_points + owned.background.global_nodes(theta.node_keys % n)
        at = np.searchsorted(serial.node_keys, glob)
        assert np.array_equal(serial.node_keys[at], glob)
        assert np.abs(theta.shifts - serial.shifts[at]).max() <= 1e-14 * serial.max_shift
        alone = cut_mesh(owned.background, phi, order=2, check_boundary=False).deformation
        at = np.searchsorted(theta.node_keys, alone.node_keys)  # the owned slab's cut tets have fewer P2 nodes
        assert np.array_equal(theta.node_keys[at], alone.node_keys)
        assert np.abs(alone.shifts - theta.shifts[at]).max() > 1e-3 * serial.max_shift  # every rank's slab ends on a cut plane


def test_order_two_needs_the_slabs(tet_sphere):
    phi, mesh = tet_sphere
    with pytest.raises(ValueError, match="order 2 runs on several ranks on the slabs of a structured box"):
        rank_cuts(partition_for(mesh, 2), 0, phi, order=2)
