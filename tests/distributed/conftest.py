"""Shared fixtures of the distributed tests (run serially and under mpiexec)."""

import numpy as np
import pytest
import scipy.sparse as sp

from cutfem.fem.forms import assemble
from cutfem.fem.spaces import CutSpace
from cutfem.fem.terms import face_jump_penalty, load, nitsche, stiffness
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import NEG
from cutfem.geometry.mesh import TetMesh
from cutfem.distributed.partition import rank_cuts
from cutfem.distributed.poisson import poisson_pieces
from cutfem.problems.common import background_for, levelset_for
from cutfem.problems.poisson import exact_u, source


@pytest.fixture(scope="module")
def torus():
    """The serial poisson-cut system of the torus at spacing 0.1 (12 cell layers): phi, the
    background, the cut, the space, K, b and the number of ghost faces."""
    phi = levelset_for("torus")
    return poisson_system(phi, background_for(phi, 0.1, "structured", None))


def poisson_system(phi, background):
    """The serial poisson-cut system on ``background`` (Nitsche gamma 10, ghost penalty 0.1): phi,
    the background, the cut, the space, K, b and the number of ghost faces."""
    cut = cut_mesh(background, phi)
    V = CutSpace(cut, NEG)
    dx = cut.dx(NEG)
    N = nitsche(cut.ds(), 10.0, g=exact_u)
    G = cut.ghost_facets(NEG)
    K = assemble(stiffness(dx) + N + 0.1 * face_jump_penalty(cut.dF(G), h_power=1), V)
    b = assemble(load(source, dx, degree=2) + N.load, V)
    return phi, background, cut, V, K, b, G.n_facets


def jittered_mesh(box, seed=0):
    """An unstructured TetMesh made from the Kuhn tets of a structured box: the interior nodes
    moved by up to 0.15 spacing at random, the nodes and the tets renumbered at random (seeded: the
    same mesh on every rank, unlike pytetwild's, whose two meshings of a box differ)."""
    rng = np.random.default_rng(seed)
    points = box.points.copy()
    inner = np.ones(len(points), dtype=bool)
    inner[box.boundary_nodes] = False
    points[inner] += rng.uniform(-0.15, 0.15, (int(inner.sum()), 3)) * box.spacing
    perm = rng.permutation(len(points))
    tets = np.argsort(perm)[box.tets][rng.permutation(box.n_tets)]
    return TetMesh(points[perm], tets, orient=True)


@pytest.fixture(scope="session")
def tet_torus():
    """The poisson-cut system of the torus on an unstructured mesh (the torus's box at spacing 0.2,
    jittered and renumbered): phi, the mesh, the cut, the space, K, b and the ghost faces."""
    phi = levelset_for("torus")
    return poisson_system(phi, jittered_mesh(background_for(phi, 0.2, "structured", None)))


@pytest.fixture(scope="session")
def tet_sphere():
    """The unit sphere and an unstructured mesh of its box at spacing 0.2 (jittered, renumbered)."""
    phi = levelset_for("sphere")
    return phi, jittered_mesh(background_for(phi, 0.2, "structured", None), seed=1)


def _summed(partition, phi, V, pieces=lambda cuts: poisson_pieces(cuts, 10.0, 0.1)):
    """The pieces of every rank of ``partition``, computed in this process and added in the
    serial numbering of ``V``: the matrix, the load and the number of faces assembled."""
    n = V.n_dofs
    K, b, faces = sp.csr_matrix((n, n)), np.zeros(n), 0
    for rank in range(partition.size):
        parts = pieces(rank_cuts(partition, rank, phi))
        faces += parts.faces
        for piece in parts.pieces:
            dofs = np.searchsorted(V.node_ids, piece.keys)
            assert np.array_equal(V.node_ids[dofs], piece.keys)  # every row is a serial unknown
            c = piece.matrix.tocoo()
            K = K + sp.csr_matrix((c.data, (dofs[c.row], dofs[c.col])), shape=(n, n))
            if piece.vector is not None:
                np.add.at(b, dofs, piece.vector)
    return K, b, faces


@pytest.fixture(scope="session")
def summed():
    """``summed(partition, phi, V, pieces=poisson's)``: every rank's pieces added up serially."""
    return _summed


@pytest.fixture(scope="session")
def first_ranks():
    """``first_ranks(size)``: a communicator of the first ``size`` ranks of COMM_WORLD (None on the
    others; the test skips when there are fewer ranks)."""
    from cutfem.distributed.launch import engine  # the MPI tests only: mpi4py may be missing

    MPI, _ = engine()
    world = MPI.COMM_WORLD

    def split(size):
        if world.size < size:
            pytest.skip(f"needs {size} ranks, runs on {world.size}")
        comm = world.Split(0 if world.rank < size else MPI.UNDEFINED, world.rank)
        return None if comm == MPI.COMM_NULL else comm

    return split
