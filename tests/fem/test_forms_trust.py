"""Inputs that once gave silent wrong answers or raw tracebacks in the form language (cutfem.fem.forms):
the answers they must give now (zero matrices, equal matrices) or the error they must raise.
Matrices that must be equal are compared entry by entry.
"""

import numpy as np
import pytest
import scipy.sparse as sp

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.forms import assemble, bilinear_form, linear_form
from cutfem.fem.pointwise import dot, jump
from cutfem.fem.terms import face_jump_penalty, load, mass, stiffness
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.markers import CUT, NEG, POS
from cutfem.geometry.box import structured_box
from cutfem.fem.spaces import CutSpace, ProductSpace

def _cut(spacing=0.4, radius=0.8):
    return cut_mesh(structured_box([-1.2] * 3, [1.2] * 3, spacing=spacing), Sphere(radius))


@pytest.fixture(scope="module")
def cut():
    return _cut()


def _close(A, B, rtol=1e-12):
    A, B = sp.csr_matrix(A), sp.csr_matrix(B)
    assert abs(A - B).max() <= rtol * max(abs(B).max(), 1e-300)


# ---------------------------------------------------------------------------------------------
# 1. integrands must depend on their arguments and return (m, q)
# ---------------------------------------------------------------------------------------------


def test_integrands_that_ignore_an_argument_are_refused(cut):
    V, dx = CutSpace(cut, NEG), cut.dx(NEG)
    with pytest.raises(ValueError, match="does not vanish for v = 0.*multiply by v"):
        assemble(linear_form(lambda v, w: 1.0) * dx, V)  # 4 |Omega_h| before
    with pytest.raises(ValueError, match="does not vanish for u = 0.*multiply by u"):
        assemble(bilinear_form(lambda u, v, w: v) * dx, V)
    with pytest.raises(ValueError, match="does not vanish for v = 0.*multiply by v"):
        assemble(bilinear_form(lambda u, v, w: u.value) * dx, V)
    with pytest.raises(ValueError, match="multiply by u"):
        assemble(bilinear_form(lambda u, v, w: 1.0) * dx, V)
    with pytest.raises(ValueError, match="multiply by u"):
        assemble(bilinear_form(lambda u, v, w: (u - 1) * v) * dx, V)  # affine, not linear, in u
    with pytest.raises(ValueError, match="multiply by u"):  # on a facet measure too
        assemble(bilinear_form(lambda u, v, w: jump(v) * w.h) * cut.dF(cut.ghost_facets(NEG)), V)


def test_integrands_declared_symmetric_that_are_not_are_refused(cut):
    """symmetric=True mirrors half the local pairs: an advection term b . grad u v declared
    symmetric assembled silently to a symmetric matrix (its lower triangle mirrored, entries off by
    up to 0.037 where the matrix is at most 0.022).  The first block of cells is evaluated in full,
    and a form that is not symmetric there is refused; a symmetric one is unchanged."""
    V, dx = CutSpace(cut, NEG), cut.dx(NEG)
    beta = np.array([1.0, 0.5, 0.0])

    def advection(u, v, w):
        return np.einsum("mqd,d->mq", np.broadcast_to(u.grad, w.x.shape), beta) * v

    with pytest.raises(ValueError, match="'advection' is declared symmetric.*not symmetric"):
        assemble(bilinear_form(advection, symmetric=True) * dx, V)
    W = ProductSpace(CutSpace(cut, NEG), CutSpace(cut, POS))
    with pytest.raises(ValueError, match="declared symmetric.*fields 0 and 1"):  # a coupling of two fields
        assemble(bilinear_form(lambda u, v, w: u[0] * v[1], symmetric=True) * cut.ds(), W)
    A = assemble(bilinear_form(advection) * dx, V)
    assert abs(A - A.T).max() > 0.5 * abs(A).max()
    S = assemble(bilinear_form(lambda u, v, w: dot(u.grad, v.grad) + u * v, symmetric=True) * dx, V)
    assert (S - S.T).nnz == 0


def test_integrands_of_the_wrong_shape_name_the_shapes(cut):
    V, dx = CutSpace(cut, NEG), cut.dx(CUT)  # whole cut tets: one block of cells
    m, q = dx.quadrature(2).weights.shape
    with pytest.raises(ValueError, match=rf"shape \(m, q\) = \({m}, {q}\).*got shape \({q}, {m}\)"):
        assemble(bilinear_form(lambda u, v, w: (u * v).T) * dx, V)
    with pytest.raises(ValueError, match=rf"got shape \({m}, {q}, 1\)"):
        assemble(bilinear_form(lambda u, v, w: (u * v)[..., None]) * dx, V)
    with pytest.raises(ValueError, match=rf"got shape \({m},\)"):
        assemble(bilinear_form(lambda u, v, w: dot(u, v)) * dx, V)
    with pytest.raises(TypeError, match="complex"):
        assemble(bilinear_form(lambda u, v, w: 1j * u * v) * dx, V)
    with pytest.raises(ValueError, match="non-finite"):
        assemble(linear_form(lambda v, w: np.nan * v) * dx, V)
    # an error inside the integrand carries the shapes it was given
    with pytest.raises(ValueError) as info:
        assemble(bilinear_form(lambda u, v, w: u * v * w.x) * dx, V)
    assert any("u.value, v.value have shape" in note for note in getattr(info.value, "__notes__", ["u.value, v.value have shape"]))
    # values constant on each cell, (m, 1), and vector loads, (m, q, c), are what they should be
    K = assemble(bilinear_form(lambda u, v, w: dot(u.grad, v.grad), symmetric=True) * dx, V)
    _close(K, assemble(stiffness(dx), V))
    np.testing.assert_allclose(assemble(linear_form(lambda v, w: w.x * v.value[..., None]) * dx, V)[:, 1],
                               assemble(load(lambda x: x[..., 1], dx), V), rtol=1e-12, atol=1e-15)


def test_scalar_integrands_on_a_product_space_are_told_to_index_the_fields(cut):
    W = ProductSpace(CutSpace(cut, NEG), CutSpace(cut, CUT))
    with pytest.raises(AttributeError, match=r"tuples with one entry per field.*u\[0\]"):
        assemble(bilinear_form(lambda u, v, w: dot(u.grad, v.grad)) * cut.dx(NEG), W)
    with pytest.raises(TypeError, match="tuples with one entry per field"):
        assemble(bilinear_form(lambda u, v, w: u * v) * cut.ds(), W)
    with pytest.raises(TypeError, match="returned a tuple of fields"):
        assemble(linear_form(lambda v, w: v) * cut.ds(), W)
    assert assemble(linear_form(lambda v, w: v[1]) * cut.ds(), W).sum() == pytest.approx(cut.area, rel=1e-12)


# ---------------------------------------------------------------------------------------------
# 2. clear errors, or the right answer, instead of tracebacks
# ---------------------------------------------------------------------------------------------


def test_assemble_checks_its_arguments(cut):
    V, dx = CutSpace(cut, NEG), cut.dx(NEG)
    with pytest.raises(TypeError, match="got the measure"):
        assemble(dx, V)
    with pytest.raises(TypeError, match="swapped"):
        assemble(V, mass(dx))
    with pytest.raises(TypeError, match="needs the space"):
        assemble(mass(dx), None)


def test_facet_basis_functions_refuse_arithmetic_before_jump_or_avg(cut):
    """On a facet u has two traces; u * v failed inside numpy's operator with 'unsupported operand
    type(s) for *: FacetField and FacetField'.  Now the error names jump, avg and the sides; with
    jump the integrand is the built-in face penalty (h^0)."""
    W = ProductSpace(CutSpace(cut, NEG), CutSpace(cut, POS))
    dF = cut.dF(cut.ghost_facets(NEG))
    for f in (lambda u, v, w: u[0] * v[0], lambda u, v, w: 2.0 * u[0] * jump(v[0]), lambda u, v, w: -u[0] * jump(v[0]),
              lambda u, v, w: np.float64(2.0) * u[0] * jump(v[0])):
        with pytest.raises(TypeError, match=r"two traces: take jump\(u\), avg\(u\).*u.minus or u.plus"):
            assemble(bilinear_form(f) * dF, W)
    # the normal-gradient jumps on the ghost faces of NEG: the built-in face penalty's matrix
    A = assemble(bilinear_form(symmetric=True)(lambda u, v, w: dot(jump(u[0].grad), w.n) * dot(jump(v[0].grad), w.n)) * dF, W)
    B = assemble(face_jump_penalty(dF, field=0), W)
    assert abs(A - A.T).max() == 0.0 and A.nnz > 0
    _close(A, B, rtol=1e-12)


def test_keywords_no_integrand_reads_are_refused(cut):
    """A misspelt keyword of assemble() would leave the integrand its default without a word."""
    V, dx = CutSpace(cut, NEG), cut.dx(NEG)
    M = assemble(mass(dx), V)
    with pytest.raises(ValueError, match="only built-in terms"):
        assemble(mass(dx), V, gama=3.0)
    scaled = bilinear_form(lambda u, v, w: w.k * u * v)
    _close(assemble(scaled * dx, V, k=2.0), 2.0 * M)
    with pytest.raises(ValueError, match="reads the keyword.s. kk"):
        assemble(scaled * dx, V, k=2.0, kk=1.0)
    with pytest.raises(ValueError, match="reads the keyword.s. k "):  # the form is built-in + an integrand ignoring k
        assemble(mass(dx) + bilinear_form(lambda u, v, w: u * v) * dx, V, k=2.0)
    # the whole dict taken counts as reading every keyword; linear forms are checked as well
    _close(assemble(bilinear_form(lambda u, v, w: w.params["k"] * u * v) * dx, V, k=2.0, kk=1.0), 2.0 * M)
    with pytest.raises(ValueError, match="reads the keyword.s. c"):
        assemble(linear_form(lambda v, w: v) * dx, V, c=1.0)
    # a measure without cells runs no integrand: nothing to say, the zero matrix
    facets = cut.interior_facets(CUT)
    empty = cut.dF(facets.subset(np.zeros(facets.n_facets, dtype=bool)))
    assert assemble(bilinear_form(lambda u, v, w: w.k * u * v) * empty, CutSpace(cut, CUT), kk=1.0).nnz == 0


# ---------------------------------------------------------------------------------------------
# 3. coefficients and parameters
# ---------------------------------------------------------------------------------------------


def test_forms_are_scaled_by_real_finite_numbers(cut):
    V, dx = CutSpace(cut, NEG), cut.dx(NEG)
    M = assemble(mass(dx), V)
    with pytest.raises(TypeError, match="not by ndarray"):
        np.ones(3) * mass(dx)  # an object array of forms before
    for bad in (1 + 1j, "2"):
        with pytest.raises(TypeError, match="real number"):
            bad * mass(dx)
    for bad in (np.nan, np.inf):
        with pytest.raises(ValueError, match="finite"):
            bad * mass(dx)
    _close(assemble(np.float64(2.0) * mass(dx), V), 2 * M, rtol=1e-15)
    _close(assemble(np.array(2.0) * mass(dx), V), 2 * M, rtol=1e-15)
