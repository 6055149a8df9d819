"""Saddle-point solves (cutfem.solvers.saddle) on the cut Stokes system of docs/math.md §14, equal-order
P1-P1 with Nitsche, ghost penalties and a Brezzi-Pitkaranta pressure stabilization, written here as
integrands over a product space of three velocity components and the pressure, bordered by a
multiplier for the pressure's mean.  MINRES with the block preconditioner against the direct
solve, its iterations under refinement, the errors against the exact solution, and the refusals
that name the cause."""

import numpy as np
import pytest
import scipy.sparse as sp

import cutfem as cf
from cutfem.fem.forms import assemble, bilinear_form, linear_form
from cutfem.fem.norms import l2_error
from cutfem.fem.pointwise import dot
from cutfem.fem.spaces import CutSpace, ProductSpace
from cutfem.fem.terms import basis_integrals, face_jump_penalty, mass
from cutfem.solvers.diagnose import SolverError

NU, GAMMA, BETA, G_U, G_P = 1.0, 20.0, 0.05, 0.1, 0.1
U = cf.Exact(["sin(x)*cos(y)", "-cos(x)*sin(y)", "0"])  # divergence free
P = cf.Exact("x**2 - y**2")  # mean zero over the ball
F = -NU * U.laplacian + P.grad


class _Multiplier:
    """A one-unknown field (the mean of the pressure's multiplier)."""

    n_dofs = 1
    h = None


def stokes(h, stabilize=True, gamma=GAMMA):
    cut = cf.cut_mesh(cf.structured_box([-1.2] * 3, [1.2] * 3, spacing=h), cf.Sphere(1.0))
    V = CutSpace(cut, cf.NEG)
    W = ProductSpace(u0=V, u1=V, u2=V, p=V)
    dx, ds, dg = cut.dx(cf.NEG), cut.ds(), cut.dF(cut.ghost_facets(cf.NEG))
    beta = BETA if stabilize else 0.0

    @bilinear_form(symmetric=True)
    def bulk(u, v, w):
        div_u = sum(u[c].grad[..., c] for c in range(3))
        div_v = sum(v[c].grad[..., c] for c in range(3))
        return (NU * sum(dot(u[c].grad, v[c].grad) for c in range(3)) - div_v * u[3] - div_u * v[3]
                - beta / NU * w.h**2 * dot(u[3].grad, v[3].grad))

    @bilinear_form(symmetric=True)
    def boundary(u, v, w):
        n = w.n
        t = sum(NU * (-dot(u[c].grad, n) * v[c] - dot(v[c].grad, n) * u[c] + gamma / w.h * u[c] * v[c]) for c in range(3))
        return t + sum(v[c] * n[..., c] for c in range(3)) * u[3] + sum(u[c] * n[..., c] for c in range(3)) * v[3]

    @linear_form
    def load(v, w):
        f = w.at(F)
        return sum(f[..., c] * v[c] for c in range(3))

    @linear_form
    def data(v, w):
        g, n = w.at(U), w.n
        t = sum(NU * (-dot(v[c].grad, n) * g[..., c] + gamma / w.h * g[..., c] * v[c]) for c in range(3))
        return t + sum(g[..., c] * n[..., c] for c in range(3)) * v[3]

    @bilinear_form(symmetric=True)
    def pressure_stabilization(u, v, w):
        return BETA / NU * w.h**2 * dot(u.grad, v.grad)

    a = bulk * dx + boundary * ds
    for c in range(3):
        a = a + NU * G_U * face_jump_penalty(dg, h_power=1, field=c)
    if stabilize:
        a = a - G_P / NU * face_jump_penalty(dg, h_power=3, field=3)
    K, b = assemble(a, W), assemble(load * dx + data * ds, W)
    S = assemble((1 / NU) * mass(dx) + pressure_stabilization * dx + G_P / NU * face_jump_penalty(dg, h_power=3), V)
    m = assemble(basis_integrals(dx), V)
    n = W.n_dofs
    column = sp.csr_matrix((m, (np.arange(3 * V.n_dofs, n), np.zeros(V.n_dofs, int))), shape=(n, 1))
    bordered = sp.bmat([[K, column], [column.T, None]]).tocsr()
    Wm = ProductSpace(u0=V, u1=V, u2=V, p=V, mean=_Multiplier())
    return dict(cut=cut, V=V, W=W, K=K, b=b, S=S, bordered=bordered, rhs=np.append(b, 0.0), Wm=Wm)


@pytest.fixture(scope="module")
def coarse():
    return stokes(0.2)


def solve_stokes(s, method):
    return cf.solve(s["bordered"], s["rhs"], space=s["Wm"], primal=["u0", "u1", "u2"], schur={"p": s["S"]}, method=method)


def errors(s, x):
    parts = s["Wm"].split(x)
    dx = s["cut"].dx(cf.NEG)
    assert abs(parts[4][0]) < 1e-6  # the multiplier of a consistent mean-zero pressure vanishes with h
    return l2_error(s["V"], np.stack(parts[:3], axis=1), U, dx), l2_error(s["V"], parts[3], P, dx)


def test_minres_agrees_with_the_direct_solve(coarse):
    x, info = solve_stokes(coarse, "minres")
    xd, infod = solve_stokes(coarse, "direct")
    assert info.method == "minres" and infod.method == "direct" and info.iterations <= 60
    assert np.abs(x - xd).max() <= 1e-6 * np.abs(xd).max()
    K = coarse["bordered"]
    assert abs(K - K.T).max() == 0.0  # symmetric, and indefinite: the pressure block is negative
    assert np.all(K.diagonal()[3 * coarse["V"].n_dofs:-1] < 0)


def test_iterations_flat_and_errors_falling():
    fine = stokes(0.1)
    x, info = solve_stokes(fine, "minres")
    coarse = stokes(0.2)
    xc, infoc = solve_stokes(coarse, "minres")
    assert max(info.iterations, infoc.iterations) <= 60
    assert max(info.iterations, infoc.iterations) / min(info.iterations, infoc.iterations) <= 1.3
    (eu, ep), (eu_c, ep_c) = errors(fine, x), errors(coarse, xc)
    assert np.log2(eu_c / eu) > 1.5 and np.log2(ep_c / ep) > 1.0  # 1.75 and 1.88 here; 2 and >= 1 asymptotically


def test_a_pressure_without_its_mean_constraint_is_named(coarse):
    with pytest.raises(SolverError, match=r"constants of field 'p' are a null vector.*mean-value constraint") as err:
        cf.solve(coarse["K"], coarse["b"], space=coarse["W"], primal=["u0", "u1", "u2"], schur={"p": coarse["S"]})
    assert err.value.cause == "singular"


def test_an_unstabilized_equal_order_pair_is_named():
    s = stokes(0.4, stabilize=False)
    with pytest.raises(SolverError, match=r"field 'p' has no block of its own.*equal-order pair"):
        solve_stokes(s, "minres")


def test_bad_declarations_are_refused(coarse):
    K, b, Wm = coarse["bordered"], coarse["rhs"], coarse["Wm"]
    with pytest.raises(ValueError, match="schur= needs a matrix for the constraint field 'p'"):
        cf.solve(K, b, space=Wm, primal=["u0", "u1", "u2"])
    with pytest.raises(ValueError, match=r"schur\['p'\] has shape"):
        cf.solve(K, b, space=Wm, primal=["u0", "u1", "u2"], schur={"p": coarse["S"][:5, :5]}, method="minres")
    with pytest.raises(ValueError, match="primal= must name some but not all"):
        cf.solve(K, b, space=Wm, primal=["u0", "u1", "u2", "p", "mean"], schur={"p": coarse["S"]})
    with pytest.raises(ValueError, match="schur= belongs to a saddle-point system"):
        cf.solve(K, b, space=Wm, schur={"p": coarse["S"]})
    with pytest.raises(SolverError, match=r"saddle-point system .* primal="):  # the SPD path's advice names the fix
        cf.solve(K, b, space=Wm, method="direct")


def test_a_nitsche_penalty_below_its_bound_is_named_on_both_paths():
    """gamma = 0.05 makes the velocity block indefinite: both paths refuse with the caller's advice
    (the saddle matrix itself stays nonsingular, so only the primal block can tell)."""
    bad = stokes(0.2, gamma=0.05)
    for method in ("direct", "minres"):
        with pytest.raises(SolverError, match=r"raise the Nitsche penalty gamma \(0.05"):
            cf.solve(bad["bordered"], bad["rhs"], space=bad["Wm"], primal=["u0", "u1", "u2"], schur={"p": bad["S"]},
                     method=method, indefinite_hint="raise the Nitsche penalty gamma (0.05 is below its bound)")


def _oseen(s, wind):
    """The Stokes system plus the advection (b . grad u, v) of each velocity component: not symmetric."""
    dx = s["cut"].dx(cf.NEG)

    b = wind[None, None, :]

    @bilinear_form
    def advection(u, v, w):
        return sum(dot(u[c].grad, b) * v[c] for c in range(3))

    A = assemble(advection * dx, s["W"])
    return s["bordered"] + sp.bmat([[A, None], [None, sp.csr_matrix((1, 1))]]).tocsr()


def test_gmres_solves_a_non_symmetric_saddle_system_and_minres_refuses_it(coarse):
    K = _oseen(coarse, np.array([2.0, -1.0, 0.5]))
    asymmetry = abs(K - K.T).max() / abs(K).max()
    assert asymmetry > 1e-3
    args = dict(space=coarse["Wm"], primal=["u0", "u1", "u2"], schur={"p": coarse["S"]})
    x, info = cf.solve(K, coarse["rhs"], method="gmres", **args)
    xd, infod = cf.solve(K, coarse["rhs"], method="auto", **args)  # 4 k unknowns: factorized
    assert info.method == "gmres" and infod.method == "direct" and info.iterations <= 100
    assert np.abs(x - xd).max() <= 1e-6 * np.abs(xd).max()
    assert np.linalg.norm(K @ x - coarse["rhs"]) <= 1e-8 * np.linalg.norm(coarse["rhs"]) * 1.01
    with pytest.raises(ValueError, match="MINRES needs a symmetric matrix.*method='gmres'"):
        cf.solve(K, coarse["rhs"], method="minres", **args)
