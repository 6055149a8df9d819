"""Tests for cutfem.fem.forms: user-written forms against the built-in terms and exact formulas.

Expected numbers come from exact P1 product formulas (the advection reference) and from the
built-in terms, themselves checked against identities in test_terms.py.
"""

import numpy as np
import pytest
import scipy.sparse as sp

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.forms import assemble, bilinear_form, linear_form
from cutfem.fem.pointwise import dot
from cutfem.fem.terms import mass
from cutfem.geometry.shapes import Sphere, Torus
from cutfem.geometry.markers import NEG
from cutfem.geometry.box import structured_box
from cutfem.fem.spaces import CutSpace, SurfaceP1Space
from cutfem.geometry.surface_meshes import torus_mesh
from cutfem.geometry.measures import surface_measure as ds
from surface_matrices import load_vector, mass_matrix, stiffness_matrix

# small spaces (a few hundred unknowns)
SMALL = {
    "meshed-torus": lambda: SurfaceP1Space(torus_mesh(16, "perturbed-flipped", seed=6)),
    "cut-sphere": lambda: CutSpace(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), Sphere(0.7, [0.03, -0.01, 0.02]))),
    "cut-torus": lambda: CutSpace(cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.4), Torus(1.0, 0.5))),
}


def relative_norm(x, scale):
    return np.abs(x).max() / scale


# ----------------------------------------------------------------------------------------------
# user-written forms
# ----------------------------------------------------------------------------------------------


@bilinear_form(symmetric=True)
def helmholtz(u, v, w):
    return dot(u.tgrad, v.tgrad) + w.k2 * u * v


@bilinear_form
def helmholtz_plain(u, v, w):
    return dot(v.tgrad, u.tgrad) + (u - u / 2) * v * (2 * w.k2)


@pytest.mark.parametrize("which", ["meshed-torus", "cut-sphere"])
def test_user_helmholtz_form_matches_builtins(which):
    V = SMALL[which]()
    k2 = 3.7
    expected = (stiffness_matrix(V) + k2 * mass_matrix(V)).toarray()
    H = assemble(helmholtz * ds(V), V, k2=k2)
    assert isinstance(H, sp.csr_matrix)
    np.testing.assert_allclose(H.toarray(), expected, rtol=0, atol=1e-13 * np.abs(expected).max())
    plain = assemble(helmholtz_plain * ds(V), V, k2=k2)
    np.testing.assert_allclose(plain.toarray(), expected, rtol=0, atol=1e-13 * np.abs(expected).max())
    with pytest.raises(AttributeError, match="k2"):
        assemble(helmholtz * ds(V), V)


@pytest.mark.parametrize("which", ["meshed-torus", "cut-sphere"])
def test_symmetric_user_form_is_exactly_symmetric(which):
    V = SMALL[which]()
    H = assemble(helmholtz * ds(V), V, k2=3.7)
    assert (H - H.T).nnz == 0


@bilinear_form
def advection(u, v, w):
    beta = np.cross(w.omega, w.x)  # rotation field, made tangential to S_h below
    beta = beta - dot(beta, w.n)[..., None] * w.n
    return dot(beta, u.tgrad) * v


MASS3 = (np.ones((3, 3)) + np.eye(3)) / 12.0


def advection_reference(V, omega):
    """B_ij = int_{S_h} (P_h (omega x x)) . (P_h grad phi_j) phi_i, piece by piece, with
    int_t phi_i x = |t| sum_ab phi_i(v_a) (1 + delta_ab) / 12 v_b (exact: both are linear on t)."""
    n = V.n_dofs
    B = np.zeros((n, n))
    if isinstance(V, SurfaceP1Space):
        tri_pts = np.asarray(V.dof_points)[V.element_dofs]
        parents = np.arange(len(tri_pts))
    else:
        tri_pts, parents = V.cut.vertices[V.cut.triangles], V.cut.triangle_tets
    for P, e in zip(tri_pts, parents):
        c = np.cross(P[1] - P[0], P[2] - P[0])
        area, nrm = 0.5 * np.linalg.norm(c), c / np.linalg.norm(c)
        dofs = V.element_dofs[e]
        X = V.dof_points[dofs]
        if len(dofs) == 3:
            E = np.column_stack([X[1] - X[0], X[2] - X[0]])
            G = E @ np.linalg.inv(E.T @ E)
            grads = np.array([-G[:, 0] - G[:, 1], G[:, 0], G[:, 1]])
            vals = np.eye(3)  # the triangle is its own element
        else:
            Ti = np.linalg.inv(np.vstack([np.ones(4), X.T]))
            grads = Ti[:, 1:]
            vals = Ti[:, :1] + grads @ P.T
        tgrads = grads - np.outer(grads @ nrm, nrm)
        moments = area * vals @ MASS3 @ P  # (k, 3): int_t phi_i x
        B[np.ix_(dofs, dofs)] += np.cross(omega, moments) @ tgrads.T
    return B


@pytest.mark.parametrize("which", ["meshed-torus", "cut-sphere", "cut-torus"])
def test_user_advection_form_matches_reference(which):
    V = SMALL[which]()
    omega = np.array([0.2, -0.3, 1.0])
    B = assemble(advection * ds(V), V, omega=omega)
    ref = advection_reference(V, omega)
    scale = np.abs(ref).max()
    np.testing.assert_allclose(B.toarray(), ref, rtol=0, atol=1e-12 * scale)
    assert np.abs(B - B.T).max() > 0.1 * scale  # a genuinely non-symmetric form
    assert relative_norm(B @ np.ones(V.n_dofs), scale) < 1e-12  # no derivative of constants


@linear_form
def weighted(v, w):
    return w.a * v * w.x[..., 0]


@linear_form(degree=2)
def components(v, w):
    return v.value[..., None] * w.x  # (m, q, 3): the three coordinate loads at once


def test_user_linear_forms_match_load():
    V = SMALL["cut-sphere"]()
    np.testing.assert_allclose(assemble(weighted * ds(V), V, a=2.0), 2.0 * load_vector(V, lambda x: x[..., 0]), rtol=1e-13, atol=1e-16)
    np.testing.assert_allclose(assemble(components * ds(V), V), load_vector(V, lambda x: x, degree=2), rtol=1e-13, atol=1e-16)


def test_lattice_terms_that_go_elsewhere_allocate_nothing(monkeypatch):
    """The surface mass of a bulk field lives on other tets than the field's lattice: the form's
    LatticeSum gets no term, makes no slots and no matrix, and the result is the triangle route."""
    from cutfem.fem.assembly import LatticeSum
    from cutfem.fem.closed_forms import _simplex_mass

    cut = cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), Sphere(0.7, [0.03, -0.01, 0.02]))
    W = CutSpace(cut, NEG)
    made = []
    monkeypatch.setattr(LatticeSum, "matrix", lambda self: made.append(self) or pytest.fail("an empty LatticeSum was turned into a matrix"))
    M = assemble(mass(cut.ds()), W)
    reference = _simplex_mass(W, cut.triangle_points, W.local_elements(cut.ds(), cut.triangle_tets), cut.triangle_areas)
    assert not made and abs(M - reference).max() == 0
    one = np.ones(W.n_dofs)
    assert one @ M @ one == pytest.approx(cut.area, rel=1e-12)


# ----------------------------------------------------------------------------------------------
# parameters: the term's own (integrand.on(measure, **params)) before the form-wide ones
# ----------------------------------------------------------------------------------------------


@bilinear_form(symmetric=True)
def scaled_mass(u, v, w):
    return w.k * u * v


def test_a_term_carries_its_own_parameters():
    V = SMALL["cut-sphere"]()
    dS = ds(V)
    M = mass_matrix(V)
    np.testing.assert_allclose(assemble(scaled_mass.on(dS, k=2.0), V).toarray(), 2.0 * M.toarray(), rtol=1e-13, atol=1e-16)
    # the term's own value before the form-wide keyword, which the other term reads
    both = assemble(scaled_mass.on(dS, k=2.0) + scaled_mass * dS, V, k=3.0)
    np.testing.assert_allclose(both.toarray(), 5.0 * M.toarray(), rtol=1e-13, atol=1e-16)
    with pytest.raises(ValueError, match=r"the term 'scaled_mass' over .* reads the keyword\(s\) kk"):
        assemble(scaled_mass.on(dS, k=1.0, kk=1.0), V)
    with pytest.raises(ValueError, match=r"keyword\(s\) h would be hidden"):
        scaled_mass.on(dS, h=1.0)
    with pytest.raises(TypeError, match="multiply an integrand by a measure"):
        scaled_mass.on(V)
