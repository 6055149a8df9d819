"""Shared fixtures of the distributed tests (run serially and under mpiexec)."""

import numpy as np
import pytest

from cutfem.fem.forms import assemble
from cutfem.fem.spaces import CutSpace
from cutfem.fem.terms import face_jump_penalty, load, nitsche, stiffness
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import NEG
from cutfem.geometry.mesh import TetMesh
from cutfem.problems.common import background_for, levelset_for
from cutfem.problems.poisson import exact_u, source


@pytest.fixture(scope="module")
def torus():
    """The serial poisson-cut system of the torus at spacing 0.1 (12 cell layers): phi, the
    background, the cut, the space, K, b and the number of ghost faces."""
    phi = levelset_for("torus")
    bg = background_for(phi, 0.1, "structured", None)
    cut = cut_mesh(bg, phi)
    V = CutSpace(cut, NEG)
    dx = cut.dx(NEG)
    N = nitsche(cut.ds(), 10.0, g=exact_u)
    G = cut.ghost_facets(NEG)
    K = assemble(stiffness(dx) + N + 0.1 * face_jump_penalty(cut.dF(G), h_power=1), V)
    b = assemble(load(source, dx, degree=2) + N.load, V)
    return phi, bg, cut, V, K, b, G.n_facets


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
    mesh = jittered_mesh(background_for(phi, 0.2, "structured", None))
    cut = cut_mesh(mesh, phi)
    V = CutSpace(cut, NEG)
    dx = cut.dx(NEG)
    N = nitsche(cut.ds(), 10.0, g=exact_u)
    G = cut.ghost_facets(NEG)
    K = assemble(stiffness(dx) + N + 0.1 * face_jump_penalty(cut.dF(G), h_power=1), V)
    b = assemble(load(source, dx, degree=2) + N.load, V)
    return phi, mesh, cut, V, K, b, G.n_facets


@pytest.fixture(scope="session")
def tet_sphere():
    """The unit sphere and an unstructured mesh of its box at spacing 0.2 (jittered, renumbered)."""
    phi = levelset_for("sphere")
    return phi, jittered_mesh(background_for(phi, 0.2, "structured", None), seed=1)
