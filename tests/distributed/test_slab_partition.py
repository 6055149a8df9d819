"""The slabs of a structured box without MPI: each rank's pieces computed in one process and added
up by their global node ids equal the serial matrix and load (docs/math.md §19), every ghost face
is assembled once, and ranks without layers, without active cells or without a cut take part."""

import numpy as np
import pytest

from cutfem.distributed.partition import SlabBox, slab_partition
from cutfem.distributed.laplace_beltrami import laplace_beltrami_pieces
from cutfem.fem.forms import assemble
from cutfem.fem.spaces import CutSpace
from cutfem.fem.terms import face_jump_penalty, load, mass, normal_gradient_penalty, tangential_stiffness
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import CUT
from cutfem.problems.common import background_for, levelset_for
from cutfem.problems.laplace_beltrami import manufactured


@pytest.mark.parametrize("counts", [[12], [6, 6], [4, 4, 4], [0, 5, 0, 7], [11, 1], [1, 1, 8, 1, 1]])
def test_pieces_add_up_to_the_serial_system(torus, counts, summed):
    """[0, 5, 0, 7]: two ranks without layers; [11, 1]: the top rank's layer lies above the torus
    (no active cell, its seam holds the faces below it); [1, 1, 8, 1, 1]: one-layer slabs."""
    phi, bg, _, V, K, b, n_faces = torus
    Ks, bs, faces = summed(slab_partition(bg, len(counts), counts), phi, V)
    x = np.random.default_rng(1).standard_normal(V.n_dofs)
    assert np.linalg.norm(Ks @ x - K @ x) <= 1e-14 * np.linalg.norm(K @ x)  # measured 3e-16
    assert np.linalg.norm(bs - b) <= 1e-14 * np.linalg.norm(b)
    assert faces == n_faces  # each ghost face once


@pytest.mark.parametrize("stabilization", ["face", "normal"])
def test_laplace_beltrami_pieces_add_up_to_the_serial_system(stabilization, summed):
    """TraceFEM on the cut tets: the tangential stiffness, mass and load over the pieces of Gamma_h
    by their owner, J_F (each interior face of the cut tets once) or the normal-gradient term."""
    phi = levelset_for("sphere")
    sol = manufactured(phi)
    bg = background_for(phi, 0.2, "structured", None)
    cut = cut_mesh(bg, phi)
    V = CutSpace(cut)
    dS = cut.ds()
    stab = (face_jump_penalty(cut.dF(cut.interior_facets(CUT)), h_power=1.0) if stabilization == "face" else
            normal_gradient_penalty(cut.dx(CUT), h_power=1.0))
    K = assemble(tangential_stiffness(dS) + mass(dS) + stab, V)
    b = assemble(load(sol.f, dS, degree=4), V)
    Ks, bs, faces = summed(slab_partition(bg, 4, [3, 0, 4, 4]), phi, V, lambda cuts: laplace_beltrami_pieces(cuts, sol, stabilization, 1.0, 1.0, 1.0, 1.0))
    x = np.random.default_rng(2).standard_normal(V.n_dofs)
    assert np.linalg.norm(Ks @ x - K @ x) <= 1e-14 * np.linalg.norm(K @ x)
    assert np.linalg.norm(bs - b) <= 1e-14 * np.linalg.norm(b)
    assert faces == (cut.interior_facets(CUT).n_facets if stabilization == "face" else 0)


def test_slab_coordinates_are_the_global_ones_bit_for_bit(torus):
    phi, bg, *_ = torus
    slab = SlabBox(bg, 5, 9)
    ids = np.arange(slab.n_points)
    assert np.array_equal(slab.node_coordinates(ids), bg.node_coordinates(slab.global_nodes(ids)))
    assert np.array_equal(slab.points, bg.node_coordinates(slab.global_nodes(ids)))
    assert slab.h == bg.h


def test_partition_counts():
    bg = background_for(levelset_for("torus"), 0.1, "structured", None)
    slabs = slab_partition(bg, 5)
    assert slabs.starts.tolist() == [0, 3, 6, 8, 10, 12]  # 12 layers: the first two ranks one more
    assert slabs.layer_owner(np.arange(12)).tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 3, 3, 4, 4]
    per = int(bg.node_shape[0] * bg.node_shape[1])
    layer = 6 * int(bg.cells[0] * bg.cells[1])
    assert slabs.node_owner([0, 3 * per - 1, 3 * per, 12 * per, 13 * per - 1]).tolist() == [0, 0, 1, 4, 4]  # the top node layer: 4
    assert slabs.cell_owner([0, 3 * layer - 1, 3 * layer, 12 * layer - 1]).tolist() == [0, 0, 1, 4]
    empty = slab_partition(bg, 3, [0, 12, 0])
    assert set(empty.node_owner(np.arange(bg.n_points)).tolist()) == {1}
    assert empty.local_meshes(0) == (None, None) and empty.local_meshes(2) == (None, None)
    with pytest.raises(ValueError, match="summing to the box's 12 layers"):
        slab_partition(bg, 2, [5, 5])
