"""Shared fixtures of the distributed tests (run serially and under mpiexec)."""

import pytest

from cutfem.fem.forms import assemble
from cutfem.fem.spaces import CutSpace
from cutfem.fem.terms import face_jump_penalty, load, nitsche, stiffness
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import NEG
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
