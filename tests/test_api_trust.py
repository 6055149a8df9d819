"""Inputs that used to give silent wrong answers, crashes or raw tracebacks: field positions of a
product space, coefficient vectors of the wrong length, measures of another background mesh, bad
element ids, bad convergence data, bad solver input and bad sizes.  Each is refused with a message
that names the problem, next to the legitimate use that still gives the right number."""

import numpy as np
import pytest
import scipy.sparse as sp

from cutfem.geometry.cut import CUT, NEG, POS, cut_mesh
from cutfem.fem.norms import fitted_rate, h1_error, l2_error, l2_h1_errors, rates
from cutfem.fem.forms import assemble
from cutfem.fem.terms import face_jump_penalty, mass
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.markers import ElementSet
from cutfem.geometry.box import structured_box
from cutfem.solvers.diagnose import condition_number
from cutfem.solvers.direct import DirectSolver
from cutfem.solvers.krylov import CGSolver
from cutfem.solvers.solve import solve
from cutfem.fem.spaces import CutSpace, ProductSpace, SurfaceP1Space
from cutfem.geometry.surface_meshes import sphere_mesh

X = lambda p: p[..., 0]  # noqa: E731
GRAD_X = lambda p: np.broadcast_to(np.array([1.0, 0.0, 0.0]), p.shape)  # noqa: E731


@pytest.fixture(scope="module")
def cut():
    return cut_mesh(structured_box([-1.2] * 3, [1.2] * 3, spacing=0.2), Sphere(1.0))


@pytest.fixture(scope="module")
def spaces(cut):
    VN, VP, VC = CutSpace(cut, NEG), CutSpace(cut, POS), CutSpace(cut, CUT)
    return VN, VP, VC, ProductSpace(VN, VP)


def laplacian_1d(n=50):
    return sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsr()


# 1. field positions of a product space -------------------------------------------------------

def test_product_space_takes_only_positions_in_range(cut, spaces):
    VN, VP, _, W = spaces
    n0 = VN.n_dofs
    for bad in (-1, -2, 2, 5, 1.5, 1.0, True):
        with pytest.raises(ValueError, match=r"position 0\.\.1 or its name; got .*the fields are \['u0', 'u1'\]"):
            W.index(bad)
    with pytest.raises(ValueError, match="position 0..1"):
        W.dofs(-1)
    with pytest.raises(ValueError, match="position 0..1"):
        W[-2]
    dg = cut.dF(cut.ghost_facets(NEG))
    with pytest.raises(ValueError, match="position 0..1"):  # used to land field 0's block in field 1's rows
        assemble(face_jump_penalty(dg, field=-2), W)
    K = assemble(face_jump_penalty(dg, field=np.int64(0)), W).tocsr()
    assert K[:n0, :n0].nnz > 0 and K[n0:, n0:].nnz == 0
    assert np.array_equal(W.dofs(1), np.arange(n0, W.n_dofs)) and W[1] is VP


# 2. coefficient vectors of the wrong length ---------------------------------------------------

def test_errors_check_the_length_of_the_coefficients(cut, spaces):
    VN, VP, VC, W = spaces
    u = lambda p: p[..., 0] + 2  # noqa: E731
    x = W.join([u(VN.dof_points), u(VP.dof_points)])
    assert l2_error(VP, W.split(x)[1], u, cut.dx(POS)) < 1e-14
    for call in (lambda: l2_error(VP, x, u, cut.dx(POS)),  # used to give 2.915
                 lambda: h1_error(VP, x, GRAD_X, cut.dx(POS)),  # used to give 21.43
                 lambda: l2_h1_errors(VP, x, lambda p: (u(p), GRAD_X(p)), cut.dx(POS))):
        with pytest.raises(ValueError, match=rf"shape \({VP.n_dofs},\) .* got \({W.n_dofs},\).*W\.split\(x\)\[k\]"):
            call()
    with pytest.raises(ValueError, match=rf"got \({VP.n_dofs - 1},\)"):  # used to be a raw IndexError
        l2_error(VP, x[: VP.n_dofs - 1], u, cut.dx(POS))
    with pytest.raises(ValueError, match=rf"got \({VC.n_dofs + 1},\)"):  # on S_h: used to give 0.0
        h1_error(VC, np.zeros(VC.n_dofs + 1), lambda p: np.zeros(p.shape))


# 3. measures of another background ------------------------------------------------------------

def test_a_measure_of_another_background_is_refused(cut, spaces):
    VN = spaces[0]
    xA = VN.dof_points[:, 0]
    shifted = cut_mesh(structured_box([-1.0, -1.2, -1.2], [1.4, 1.2, 1.2], spacing=0.2), Sphere(0.8, center=(0.2, 0, 0)))
    for call in (lambda: l2_error(VN, xA**2, lambda p: p[..., 0] ** 2, shifted.dx(NEG)),  # used to give 0.0586
                 lambda: assemble(mass(shifted.dx(NEG)), VN),
                 lambda: l2_error(VN, xA, X, shifted.ds()),
                 lambda: CutSpace(cut, shifted.elements(NEG))):
        with pytest.raises(ValueError, match="another background mesh"):
            call()
    VB = CutSpace(shifted, NEG)
    assert l2_error(VB, VB.dof_points[:, 0] ** 2, lambda p: p[..., 0] ** 2, shifted.dx(NEG)) == pytest.approx(0.0105331, rel=1e-4)
    # the same box built again, another cut of it: the same tets, so its measures serve the field
    other = cut_mesh(structured_box([-1.2] * 3, [1.2] * 3, spacing=0.2), Sphere(0.8, center=(0.1, 0, 0)))
    M = assemble(mass(other.dx(NEG)), VN)
    one = np.ones(VN.n_dofs)
    assert one @ M @ xA == pytest.approx(0.1 * other.dx(NEG).size, rel=1e-12)
    assert l2_error(VN, xA, X, other.ds()) < 1e-14


# 4. element and facet ids ---------------------------------------------------------------------

def test_element_set_ids_are_checked(cut):
    bg = cut.background
    for bad in ([bg.n_tets], [10**9], [-1], [bg.n_tets, bg.n_tets + 7]):  # 10**9 and -1 used to segfault
        with pytest.raises(ValueError, match=rf"must lie in \[0, {bg.n_tets}\)"):
            ElementSet(bg, np.array(bad), cut=cut)
    with pytest.raises(ValueError, match="must not repeat a tet"):  # [5, 5, 5] used to count three times
        ElementSet(bg, np.array([5, 5, 5]), cut=cut)
    with pytest.raises(ValueError, match="integer background tet ids, got an array of dtype float64"):
        ElementSet(bg, np.array([1.5, 2.7]), cut=cut)
    with pytest.raises(ValueError, match="flatnonzero"):
        ElementSet(bg, np.ones(bg.n_tets, bool), cut=cut)
    es = ElementSet(bg, np.array([7, 5]), cut=cut)
    assert cut.dx(es).size == pytest.approx(2 * bg.tet_volume, rel=1e-14)
    assert ElementSet(bg, np.array([], dtype=np.int64), cut=cut).n_elements == 0


def test_facet_subset_takes_masks_and_indices(cut):
    fs = cut.interior_facets(CUT)
    mask = np.zeros(fs.n_facets, bool)
    mask[[0, 4, 9]] = True
    by_index = fs.subset(np.array([0, 4, 9]))
    assert by_index.n_facets == 3 and np.array_equal(by_index.pairs, fs.subset(mask).pairs)
    with pytest.raises(ValueError, match=rf"boolean mask of the facets must have shape \({fs.n_facets},\), got \(5,\)"):
        fs.subset(np.ones(5, bool))
    with pytest.raises(ValueError, match=rf"facet indices must lie in \[0, {fs.n_facets}\)"):
        fs.subset([fs.n_facets])
    with pytest.raises(ValueError, match="must not repeat a facet"):
        fs.subset([1, 1])
    with pytest.raises(ValueError, match="boolean mask .* or integer facet indices"):
        fs.subset(np.ones(fs.n_facets))


# 5. convergence data --------------------------------------------------------------------------

def test_rates_refuse_bad_levels():
    with pytest.raises(ValueError, match="same length"):  # used to broadcast to [2.0, 2.06]
        rates([0.2, 0.1], [1, 0.25, 0.06])
    with pytest.raises(ValueError, match="consecutive levels need different h"):  # used to give inf
        rates([0.2, 0.2], [1.0, 0.25])
    with pytest.raises(ValueError, match=r"positive and finite .* errors\[1\] = -0.25"):  # used to give nan
        rates([0.2, 0.1], [1.0, -0.25])
    with pytest.raises(ValueError, match=r"h\[1\] = 0.0"):
        rates([0.2, 0.0], [1.0, 0.25])
    with pytest.raises(ValueError, match="two levels of different h"):  # used to give 0.0 with a RankWarning
        fitted_rate([0.2], [1.0])
    with pytest.raises(ValueError, match="two levels of different h"):
        fitted_rate([0.2, 0.2], [1.0, 0.5])
    # a level without an error: None (or NaN) gives NaN next to it, and is left out of the fit
    np.testing.assert_allclose(rates([0.4, 0.2, 0.1], [1.6, None, 0.1]), [np.nan, np.nan])
    h = np.array([0.4, 0.2, 0.1, 0.05])
    assert fitted_rate(h, [3 * 0.16, None, 3 * 0.01, 3 * 0.0025]) == pytest.approx(2.0, rel=1e-12)
    np.testing.assert_allclose(rates(h, 3 * h**2), [2.0, 2.0, 2.0], rtol=1e-12)


# 6. exact solutions and product spaces in the errors -----------------------------------------

def test_error_functionals_say_what_they_need(cut, spaces):
    VN, VP, _, W = spaces
    uh = VN.dof_points[:, 0]
    with pytest.raises(ValueError, match=r"must return the pair \(u\(x\).*got ndarray of shape"):
        l2_h1_errors(VN, uh, X, cut.dx(NEG))
    with pytest.raises(ValueError, match="got a tuple of length 3"):
        l2_h1_errors(VN, uh, lambda p: (X(p), GRAD_X(p), 1), cut.dx(NEG))
    l2, h1 = l2_h1_errors(VN, uh, lambda p: (X(p), GRAD_X(p)), cut.dx(NEG))
    assert l2 < 1e-14 and h1 < 1e-13
    with pytest.raises(ValueError, match=r"per field.*\['u0', 'u1'\].*l2_error\(W\[k\], W\.split\(x\)\[k\]"):
        l2_error(W, np.zeros(W.n_dofs), X, cut.dx(NEG))


# 7. solver entry ------------------------------------------------------------------------------

def test_solver_entry_checks(spaces):
    A = laplacian_1d()
    n = A.shape[0]
    b = np.ones(n)
    with pytest.raises(ValueError, match=r"no columns \(shape \(50, 0\)\)"):
        solve(A, np.ones((n, 0)))
    with pytest.raises(ValueError, match="no columns"):
        CGSolver(A, "jacobi").solve(np.ones((n, 0)))
    for call in (lambda: solve(sp.csr_matrix((0, 0)), np.ones(0)), lambda: DirectSolver(sp.csr_matrix((0, 0)))):
        with pytest.raises(ValueError, match="the system is empty"):
            call()
    for tol in (10, 1.0, 0.0, np.nan):  # tol=10 used to return x = 0 after 0 iterations
        with pytest.raises(ValueError, match="tol must be a positive relative residual below 1"):
            solve(A, b, method="cg-jacobi", tol=tol)
    with pytest.raises(ValueError, match="below 1"):
        CGSolver(A, "jacobi", tol=5)
    for pivot_tol in (-1, np.nan, 2, "x"):  # -1 used to call this SPD matrix indefinite
        with pytest.raises(ValueError, match=r"pivot_tol must be a number in \[0, 1\)"):
            DirectSolver(A, pivot_tol=pivot_tol)
    assert np.allclose(A @ DirectSolver(A, pivot_tol=0).solve(b), b)
    with pytest.raises(ValueError, match=r"x0 must be a finite array: it has 1 non-finite"):
        CGSolver(A, "jacobi").solve(b, x0=np.r_[np.nan, np.zeros(n - 1)])
    VN = spaces[0]
    for method in ("cg-mg", "cg-amg", "direct"):
        with pytest.raises(ValueError, match=rf"the space has {VN.n_dofs} unknowns and the matrix {n}"):
            solve(A, b, method=method, space=VN)


def test_condition_number_refuses_bad_input_and_keeps_its_verdicts():
    A = laplacian_1d()
    B = A.tolil()
    B[1, 1] = np.nan
    with pytest.raises(ValueError, match="condition_number: the matrix has 1 non-finite"):  # used to be an ArpackError
        condition_number(B.tocsr())
    with pytest.raises(ValueError, match="condition_number: the matrix must be square"):
        condition_number(A[:, :-1])
    kappa = condition_number(A)
    assert kappa.cause is None and float(kappa) == pytest.approx(1 / np.tan(np.pi / (2 * 51)) ** 2, rel=1e-8)
    assert condition_number(-A).cause == "indefinite"


# 8. sizes -------------------------------------------------------------------------------------

def test_mesh_sizes_are_checked(cut):
    for h in (-1, 0, np.nan, np.inf):
        with pytest.raises(ValueError, match=r"h \(the mesh size\) must be a finite positive number"):
            CutSpace(cut, NEG, h=h)
        with pytest.raises(ValueError, match=r"h \(the mesh size\) must be a finite positive number"):
            SurfaceP1Space(sphere_mesh(1), h=h)
    assert CutSpace(cut, NEG, h=0.25).h == 0.25


def test_structured_box_arguments_are_checked():
    with pytest.raises(ValueError, match=r"lower must be 3 numbers \(x, y, z\), got 0"):
        structured_box(0, 1, spacing=0.5)
    with pytest.raises(ValueError, match="lower must be 3 numbers"):
        structured_box([0, 0], [1, 1], spacing=0.1)
    with pytest.raises(ValueError, match=r"upper must be 3 numbers"):
        structured_box([0, 0, 0], [[1, 1, 1]], spacing=0.1)
    with pytest.raises(ValueError, match=r"spacing must be a number or 3 numbers"):
        structured_box([0] * 3, [1] * 3, spacing=[0.5, 0.25])
    with pytest.raises(ValueError, match=r"cells must be a whole number or 3 whole numbers .* got 2.5"):  # used to give 2
        structured_box([0] * 3, [1] * 3, cells=2.5)
    with pytest.raises(ValueError, match="cells must be"):
        structured_box([0] * 3, [1] * 3, cells=(2, 3))
    assert structured_box([0] * 3, [1] * 3, cells=3.0).cells.tolist() == [3, 3, 3]
    box = structured_box([0] * 3, [1] * 3, spacing=[0.5, 0.25, 0.5])
    assert box.cells.tolist() == [2, 4, 2]


def test_facet_measure_takes_a_facet_set_only():
    cut = cut_mesh(structured_box([-1.2] * 3, [1.2] * 3, spacing=0.4), Sphere(1.0))
    assert cut.dF(cut.interior_facets(CUT)).facets.n_facets > 0
    for wrong in (cut.elements(CUT), None, CUT):
        with pytest.raises(TypeError, match="dF takes a FacetSet"):
            cut.dF(wrong)


def test_condition_number_refuses_a_nonsymmetric_matrix():
    A = sp.diags([2.0] * 30) - sp.diags([0.5] * 29, 1) - sp.diags([0.5] * 29, -1)
    kappa = condition_number(A.tocsr())
    lam = 2.0 - np.cos(np.pi * np.arange(1, 31) / 31)  # eigenvalues of tridiag(-0.5, 2, -0.5); the scaling keeps their ratio
    assert kappa.cause is None and float(kappa) == pytest.approx(lam.max() / lam.min(), rel=1e-10)
    B = (A + sp.diags([0.3] * 29, 1)).tocsr()
    with pytest.raises(ValueError, match="not symmetric"):
        condition_number(B)


def test_errors_name_what_is_not_finite(cut):
    """l2_error / h1_error returned nan when the exact function or the coefficients held a nan or
    inf (a load refuses them); the cause is now named, and only checked when a sum is not finite."""
    from cutfem.fem.norms import h1_error, l2_error

    V, dx = CutSpace(cut, NEG), cut.dx(NEG)
    u = np.ones(V.n_dofs)
    assert l2_error(V, u, lambda x: np.ones(x.shape[:2]), dx) < 1e-14
    with pytest.raises(ValueError, match=r"the exact solution is not finite at \d+ quadrature point\(s\), e.g. x = \[0\.3"):
        l2_error(V, u, lambda x: np.where(x[..., 0] > 0.3, np.nan, 1.0), dx)
    with pytest.raises(ValueError, match="the exact gradient is not finite"):
        h1_error(V, u, lambda x: np.full(x.shape, np.inf), dx)
    u[3] = np.nan
    with pytest.raises(ValueError, match=r"the discrete coefficients are not finite \(1 of them\)"):
        l2_error(V, u, lambda x: np.ones(x.shape[:2]), dx)
    S = SurfaceP1Space(sphere_mesh(2))
    with np.errstate(all="ignore"), pytest.raises(ValueError, match="the exact solution is not finite"):
        l2_error(S, np.ones(S.n_dofs), lambda x: np.log(x[..., 0]))
