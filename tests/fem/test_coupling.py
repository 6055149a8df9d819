"""The built-in coupling terms (cutfem.fem.coupling): divergence and mean_constraint, against their
quadrature route and against exact identities for linear fields."""

import numpy as np
import pytest

import cutfem as cf
from cutfem.fem.coupling import divergence, mean_constraint


@pytest.fixture(scope="module")
def stokes_space():
    cut = cf.cut_mesh(cf.structured_box([-1.1] * 3, [1.1] * 3, spacing=0.25), cf.Sphere(0.83))
    V = cf.CutSpace(cut, cf.NEG)
    W = cf.ProductSpace(u=cf.VectorSpace(V), p=V, mean=cf.RealSpace())
    return cut, V, W


def test_divergence_equals_its_quadrature_route_and_is_symmetric(stokes_space):
    cut, V, W = stokes_space
    form = divergence(cut.dx(cf.NEG))
    A, R = cf.assemble(form, W), cf.assemble(form.by_quadrature(), W)
    assert abs(A - R).max() <= 1e-14 * abs(R).max()
    assert abs(A - A.T).max() == 0.0
    n_u = W.fields[0].n_dofs
    assert A[:n_u, :n_u].nnz == 0 and A[n_u:, n_u:].nnz == 0  # only the velocity-pressure blocks


def test_divergence_of_a_linear_velocity_is_its_trace_times_the_basis_integrals(stokes_space):
    """u = M x is P1 exactly: -(div u, q) = -tr(M) (1, q) for every pressure basis function q."""
    cut, V, W = stokes_space
    dx = cut.dx(cf.NEG)
    M = np.array([[1.0, 2.0, -1.0], [0.5, -3.0, 0.25], [4.0, 1.0, 0.75]])
    u = W["u"].flat(V.dof_points @ M.T)
    A = cf.assemble(divergence(dx), W)
    x = np.zeros(W.n_dofs)
    x[W.dofs("u")] = u
    q_rows = (A @ x)[W.dofs("p")]
    expected = -np.trace(M) * cf.assemble(cf.basis_integrals(dx), V)
    np.testing.assert_allclose(q_rows, expected, rtol=0, atol=1e-13 * np.abs(expected).max())


def test_mean_constraint_is_the_basis_integrals_as_row_and_column(stokes_space):
    cut, V, W = stokes_space
    dx = cut.dx(cf.NEG)
    A = cf.assemble(mean_constraint(dx), W)
    last = W.dofs("mean")[0]
    integrals = cf.assemble(cf.basis_integrals(dx), V)
    np.testing.assert_allclose(A[last].toarray().ravel()[W.dofs("p")], integrals, rtol=1e-15)
    assert A[last].toarray().ravel()[W.dofs("p")].sum() == pytest.approx(dx.size, rel=1e-12)
    assert abs(A - A.T).max() == 0.0 and A.nnz == 2 * np.count_nonzero(integrals)
    R = cf.assemble(mean_constraint(dx).by_quadrature(), W)
    assert abs(A - R).max() <= 1e-14 * abs(R).max()


def test_coupling_terms_name_a_wrong_space(stokes_space):
    cut, V, W = stokes_space
    dx = cut.dx(cf.NEG)
    with pytest.raises(TypeError, match="ProductSpace"):
        cf.assemble(divergence(dx), V)
    with pytest.raises(TypeError, match="must be a VectorSpace"):
        cf.assemble(divergence(dx, velocity="p", pressure="p"), W)
    with pytest.raises(TypeError, match="must be a RealSpace"):
        cf.assemble(mean_constraint(dx, field="p", multiplier="p"), W)
    with pytest.raises(TypeError, match="volume"):
        divergence(cut.ds())
    with pytest.raises(TypeError, match="not over facets"):
        mean_constraint(cut.dF(cut.ghost_facets(cf.NEG)))


def test_divergence_by_parts_is_the_divergence_plus_the_boundary_flux(stokes_space):
    """(v, grad p) = -(div v, p) + (v . n, p)_Gamma_h: the divergence theorem on the polyhedral Omega_h."""
    cut, V, W = stokes_space
    dx, ds = cut.dx(cf.NEG), cut.ds()

    @cf.bilinear_form(symmetric=True)
    def flux(u, v, w):
        return cf.dot(v[0].value, w.n) * u[1] + cf.dot(u[0].value, w.n) * v[1]

    A = cf.assemble(divergence(dx, by_parts=True), W)
    R = cf.assemble(divergence(dx, by_parts=True).by_quadrature(), W)
    C = cf.assemble(divergence(dx) + flux * ds, W)
    assert abs(A - R).max() <= 1e-14 * abs(R).max()
    assert abs(A - C).max() <= 1e-13 * abs(C).max()
    assert abs(A - A.T).max() == 0.0


def test_stiffness_with_h_power_weights_each_cell_by_its_size():
    """sum_T h_T^a (grad u, grad v)_{T ∩ Omega_h}: the exact path against the quadrature route (which
    reads w.h per cell), and against h^a times the plain stiffness on a structured box (one h)."""
    cut = cf.cut_mesh(cf.structured_box([-1.1] * 3, [1.1] * 3, spacing=0.25), cf.Sphere(0.83))
    V, dx = cf.CutSpace(cut, cf.NEG), cut.dx(cf.NEG)
    A = cf.assemble(cf.stiffness(dx, h_power=2), V)
    assert abs(A - cf.assemble(cf.stiffness(dx, h_power=2).by_quadrature(), V)).max() <= 1e-14 * abs(A).max()
    h = dx.h
    assert np.ptp(h) == 0.0  # one size on the structured box
    assert abs(A - h[0] ** 2 * cf.assemble(cf.stiffness(dx), V)).max() <= 1e-14 * abs(A).max()
