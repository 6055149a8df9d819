"""The systems shared by the tests of cutfem.solvers: a cut torus at spacing 0.1 and its SPD
systems (with the meshed Laplace-Beltrami system of an icosphere), a small cut sphere, and the cut
torus at spacing 0.05 of the multigrid tests (each fixture built once per test module)."""

import pytest

from cutfem.fem.spaces import CutSpace, SurfaceP1Space
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.shapes import Sphere, Torus
from cutfem.geometry.box import structured_box
from cutfem.geometry.surface_meshes import sphere_mesh
from surface_matrices import face_matrix, mass_matrix, stiffness_matrix


@pytest.fixture(scope="module")
def cut_torus():
    return CutSpace(cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.1), Torus()))


@pytest.fixture(scope="module")
def systems(cut_torus):
    """SPD systems: meshed Laplace-Beltrami A + M, stabilized cut mass and cut Laplace-Beltrami."""
    S = SurfaceP1Space(sphere_mesh(4))
    V = cut_torus
    M, A, J = mass_matrix(V), stiffness_matrix(V), face_matrix(V)
    return {
        "meshed-lb": stiffness_matrix(S) + mass_matrix(S),
        "cut-mass": M + 0.1 * J,
        "cut-lb": A + M + 0.1 * J,
    }


@pytest.fixture(scope="module")
def small_cut_sphere():
    return CutSpace(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), Sphere(0.7, [0.03, -0.01, 0.02])))


@pytest.fixture(scope="module")
def torus_space():
    return CutSpace(cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.05), Torus()))
