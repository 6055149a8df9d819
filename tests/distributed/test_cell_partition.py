"""The cell partition of an unstructured background without MPI: each rank's pieces computed in one
process and added up by their global node ids equal the serial matrix and load (docs/math.md §19),
every ghost-penalty and J_F face is assembled once, ranks without cells or without active cells
take part, and the nodal values follow the serial zero rule at the edge of a rank's cells."""

import numpy as np
import pytest

from cutfem.distributed.laplace_beltrami import laplace_beltrami_pieces
from cutfem.distributed.partition import partition_for, rank_cuts
from cutfem.distributed.unstructured import SubMesh, cell_partition, recursive_bisection
from cutfem.fem.forms import assemble
from cutfem.fem.spaces import CutSpace
from cutfem.fem.terms import face_jump_penalty, load, mass, tangential_stiffness
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import CUT
from cutfem.geometry.nodal_values import snapped_nodal_values
from cutfem.problems.laplace_beltrami import manufactured


def by_hand(mesh, V):
    """5 ranks: 1 owns no cell, 4 owns the cells above z = 0.45 that carry no unknown (no active
    cell), the others the rest by bisection."""
    centroids = mesh.points[mesh.tets].mean(axis=1)
    owner = np.array([0, 2, 3])[recursive_bisection(centroids, 3)]
    idle = np.ones(mesh.n_tets, dtype=bool)
    idle[V.elements.tet_ids] = False
    owner[idle & (centroids[:, 2] > 0.45)] = 4
    return cell_partition(mesh, 5, owner)


@pytest.mark.parametrize("size", [1, 2, 3, 5, "by hand"])
def test_pieces_add_up_to_the_serial_system(tet_torus, size, summed):
    phi, mesh, _, V, K, b, n_faces = tet_torus
    partition = by_hand(mesh, V) if size == "by hand" else partition_for(mesh, size)
    Ks, bs, faces = summed(partition, phi, V)
    x = np.random.default_rng(1).standard_normal(V.n_dofs)
    assert np.linalg.norm(Ks @ x - K @ x) <= 1e-14 * np.linalg.norm(K @ x)  # measured 2e-16
    assert np.linalg.norm(bs - b) <= 1e-14 * np.linalg.norm(b)
    assert faces == n_faces  # each ghost face once
    if size == "by hand":
        assert rank_cuts(partition, 1, phi).owned is None
        idle = rank_cuts(partition, 4, phi)
        assert idle.owned is not None and CutSpace(idle.owned).n_dofs == 0 and idle.owned.n_tets == 0


def test_laplace_beltrami_pieces_add_up_to_the_serial_system(tet_sphere, summed):
    """TraceFEM on the cut tets of an unstructured mesh: J_F on every interior face of the cut tets once."""
    phi, mesh = tet_sphere
    sol = manufactured(phi)
    cut = cut_mesh(mesh, phi)
    V = CutSpace(cut)
    dS = cut.ds()
    K = assemble(tangential_stiffness(dS) + mass(dS) + face_jump_penalty(cut.dF(cut.interior_facets(CUT)), h_power=1.0), V)
    b = assemble(load(sol.f, dS, degree=4), V)
    Ks, bs, faces = summed(partition_for(mesh, 3), phi, V,
                           lambda cuts: laplace_beltrami_pieces(cuts, sol, "face", 1.0, 1.0, 1.0, 1.0))
    x = np.random.default_rng(2).standard_normal(V.n_dofs)
    assert np.linalg.norm(Ks @ x - K @ x) <= 1e-14 * np.linalg.norm(K @ x)
    assert np.linalg.norm(bs - b) <= 1e-14 * np.linalg.norm(b)
    assert faces == cut.interior_facets(CUT).n_facets


def test_bisection_ghosts_and_owners(tet_torus):
    _, mesh, *_ = tet_torus
    centroids = mesh.points[mesh.tets].mean(axis=1)
    for size in (2, 3, 7):
        owner = recursive_bisection(centroids, size)
        counts = np.bincount(owner, minlength=size)
        assert counts.min() >= mesh.n_tets // size and counts.max() <= mesh.n_tets // size + 1
        assert np.array_equal(owner, recursive_bisection(centroids, size))
    owner = recursive_bisection(centroids, 2)  # the longest side of the torus's box is x (or y): one cut plane
    axis = int(np.argmax(np.ptp(centroids, axis=0)))
    assert centroids[owner == 0, axis].max() <= centroids[owner == 1, axis].min()
    partition = cell_partition(mesh, 2, owner)
    # ghosts: the other rank's cells that share a face with the rank's cells
    shared = {frozenset(f) for t in np.flatnonzero(owner == 0) for f in _faces(mesh.tets[t])}
    expected = [t for t in np.flatnonzero(owner == 1) if any(frozenset(f) in shared for f in _faces(mesh.tets[t]))]
    assert partition.ghosts(0).tolist() == expected
    # a node's owner: the owner of its lowest-id cell
    lowest = np.full(mesh.n_points, mesh.n_tets)
    np.minimum.at(lowest, mesh.tets.reshape(-1), np.repeat(np.arange(mesh.n_tets), 4))
    assert np.array_equal(partition.node_owner(np.arange(mesh.n_points)), owner[lowest])
    owned, seam = partition.local_meshes(0)
    assert isinstance(owned, SubMesh) and owned.h == mesh.h
    assert np.array_equal(owned.points, mesh.points[owned.global_nodes(np.arange(owned.n_points))])
    assert np.array_equal(mesh.tets[owned.global_tets(np.arange(owned.n_tets))],
                          owned.global_nodes(owned.tets))  # the same tets, vertices in the same order
    assert np.all(np.diff(seam.global_tets(np.arange(seam.n_tets))) > 0)
    with pytest.raises(ValueError, match="a rank in \\[0, 2\\)"):
        cell_partition(mesh, 2, owner + 1)


def _faces(tet):
    return [[tet[j] for j in range(4) if j != k] for k in range(4)]


def test_nodal_values_take_the_tolerance_of_every_cell_around_a_node(tet_torus):
    """A node at the edge of a rank's cells whose |phi| is below 1e-12 of a neighbour's value only
    in a cell the rank does not hold snaps to zero as in the serial run: the tolerance is taken
    over the ring of cells around the rank's nodes."""
    phi, mesh, *_ = tet_torus
    values = phi.value(mesh.points)
    partition = partition_for(mesh, 2)
    _, seam = partition.local_meshes(0)
    held = np.zeros(mesh.n_tets, dtype=bool)
    held[seam.global_tets(np.arange(seam.n_tets))] = True
    held[partition.cells(0)] = True
    local = np.zeros(mesh.n_points, dtype=bool)
    local[mesh.tets[held]] = True
    # a node of the rank with a cell it does not hold, and a node of that cell in no held cell around the node
    for node in np.flatnonzero(local):
        around = np.flatnonzero(np.any(mesh.tets == node, axis=1))
        near = set(mesh.tets[around[held[around]]].reshape(-1))
        far = [j for j in mesh.tets[around[~held[around]]].reshape(-1) if j not in near]
        if far:
            break
    values[node], values[far[0]] = 1e-10, 1e3  # 1e-10 <= 1e-12 * 1e3: zero serially, not by the held cells alone
    serial = snapped_nodal_values(mesh, values)
    assert serial[node] == 0.0
    cuts = rank_cuts(partition, 0, values)
    for cut in (cuts.owned, cuts.seam):
        ids = cut.background.global_nodes(np.arange(cut.background.n_points))
        assert np.array_equal(cut.background_values, serial[ids])


def test_the_cut_of_part_of_a_mesh_may_end_on_its_boundary_faces(tet_torus):
    """With check_boundary=False the cut of some cells of a mesh (half the torus's mesh) keeps the
    pieces of S_h in them, open along the faces where the cells end inside the bounding box."""
    phi, mesh, cut, *_ = tet_torus
    half = SubMesh(mesh, np.flatnonzero(mesh.points[mesh.tets].mean(axis=1)[:, 0] < 0.05))
    part = cut_mesh(half, phi, check_boundary=False)
    ids = half.global_tets(np.arange(half.n_tets))
    assert not part.is_closed
    assert part.n_tets == np.isin(cut.tet_ids, ids).sum() and part.n_triangles == np.isin(cut.tet_ids[cut.triangle_tets], ids).sum()
