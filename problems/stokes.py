"""Stokes flow in a cut domain: equal-order P1-P1, Nitsche, ghost penalties, a pressure
stabilization and a mean-value multiplier (Burman-Hansbo, M2AN 48, 2014; docs/math.md §14).

-nu Lap u + grad p = f, div u = 0 in Omega = {phi < 0}, u = g on Gamma.  Find (u_h, p_h, lam) in
[V_h^NEG]^3 x V_h^NEG x R with, for all (v, q, mu),

    nu (grad u, grad v) + Nitsche_nu,gamma(u, v) - (div v, p) + (v . n, p)_Gamma - (div u, q) + (u . n, q)_Gamma
      + nu gamma_u g_1(u, v) - (gamma_p / nu) g_3(p, q) - (beta / nu) sum_T h_T^2 (grad p, grad q)_T
      + (p, mu) + (q, lam)
    = (f, v) + nu Nitsche-load(g, v) + (g . n, q)_Gamma,

g_a(u, v) = sum_{F ghost} h_F^a ([d_n u], [d_n v])_F (the velocity per component).  The two coupling
terms on a side are one volume term, -(div v, p) + (v . n, p)_Gamma = (v, grad p) over Omega_h (the
divergence theorem, exact for P1: ``divergence(dx, by_parts=True)``), and the Brezzi-Pitkaranta term
is ``stiffness(dx, h_power=2)``: both assembled by exact P1 paths.  The matrix is
symmetric indefinite: MINRES with the block preconditioner diag(multigrid on the velocity block,
multigrid on S = (1/nu) M_p + the pressure's stabilization), the multiplier by its Schur number
(:mod:`cutfem.solvers.saddle`), or a factorization when small.

Manufactured solution (cf.Exact): u = curl A, A = (sin y sin z, sin z sin x, sin x sin y), divergence
free; p = x y z + x^2 - y^2; f = -nu Lap u + grad p.  The pressure is compared up to its mean over
Omega_h (the discrete pressure has mean zero there).  Expected: L2 error of u O(h^2), H1 O(h), L2
of p O(h) or better.
"""

from __future__ import annotations

import numpy as np

from cutfem.fem.coupling import divergence, mean_constraint
from cutfem.fem.exact import Exact
from cutfem.fem.forms import assemble, linear_form
from cutfem.fem.norms import l2_error, l2_h1_errors
from cutfem.fem.pointwise import dot
from cutfem.fem.spaces import CutSpace, ProductSpace, RealSpace, VectorSpace
from cutfem.fem.terms import face_jump_penalty, load, mass, nitsche, stiffness
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import NEG
from cutfem.runs.registry import H_BACKGROUND, LazyFields, Param, register
from cutfem.runs.runner import Timer
from cutfem.solvers.solve import solve

from .common import (finish_record, DOMAIN_PARAMS, BULK_BYTES_PER_TET, SHAPE_PARAMS, background_for, check_bulk_memory,
                     check_ghost_penalty, check_nitsche_penalty, levelset_for)

_A = Exact(["sin(y)*sin(z)", "sin(z)*sin(x)", "sin(x)*sin(y)"])
VELOCITY = _A.curl
PRESSURE = Exact("x*y*z + x**2 - y**2")
VELOCITY_GRADIENT = VELOCITY.grad

DEFINITIONS = {
    "h": H_BACKGROUND,
    "dofs": "unknowns: 3 velocity components and the pressure on the nodes of the tets of NEG, and the multiplier",
    "l2_error_velocity": "||u_h - u||_L2(Omega_h) (degree-4 quadrature on the whole tets and cut parts)",
    "h1_error_velocity": "||grad u_h - grad u||_L2(Omega_h)",
    "l2_error_pressure": "||p_h - (p - mean_Omega_h p)||_L2(Omega_h): the pressure up to its mean",
}


@linear_form
def normal_data(v, w):
    """(g . n, q) on Gamma."""
    return dot(w.at(VELOCITY), w.n) * v[1]


def source(nu):
    """The load f = -nu Lap u + grad p of the manufactured solution."""
    return -nu * VELOCITY.laplacian + PRESSURE.grad


@register(
    "stokes-cut",
    summary="Stokes flow in {phi < 0}, P1-P1 with Nitsche, ghost penalties and a pressure stabilization; MINRES (docs/math.md §14)",
    levels=[0.2, 0.1, 0.05, 0.025],
    level_name="spacing",
    definitions=DEFINITIONS,
    params=[
        *DOMAIN_PARAMS,
        Param("nu", float, 1.0, "viscosity nu", positive=True),
        Param("gamma", float, 20.0, "Nitsche penalty gamma (times nu)", positive=True),
        Param("gamma_u", float, 0.1, "ghost penalty of the velocity (times nu, h_F)", minimum=0),
        Param("gamma_p", float, 0.1, "ghost penalty of the pressure (over nu, h_F^3)", minimum=0),
        Param("beta", float, 0.05, "Brezzi-Pitkaranta pressure stabilization beta (over nu, h_T^2)", positive=True),
        Param("solver", str, "auto", "linear solver: auto (direct up to 5000 unknowns), minres or direct",
              choices=("auto", "minres", "direct")),
        *SHAPE_PARAMS,
    ],
)
def stokes_cut(spacing, surface, background, box, nu, gamma, gamma_u, gamma_p, beta, solver, R, r, radius, axes):
    """One level of the cut Stokes problem."""
    notes = check_ghost_penalty(gamma_u, "--gamma-u") + check_ghost_penalty(gamma_p, "--gamma-p") + check_nitsche_penalty(gamma)
    t = Timer()
    with t("geometry"):
        phi = levelset_for(surface, R, r, radius, axes)
        bg = background_for(phi, spacing, background, box)
        check_bulk_memory(bg, phi, (NEG,), BULK_BYTES_PER_TET["stokes-cut"], spacing)
        cut = cut_mesh(bg, phi)
        V = CutSpace(cut, NEG)
        W = ProductSpace(u=VectorSpace(V), p=V, mean=RealSpace())
        dx, ds, dg = cut.dx(NEG), cut.ds(), cut.dF(cut.ghost_facets(NEG))
    with t("assembly"):
        N = nitsche(ds, gamma, g=VELOCITY, field="u")
        f = source(nu)
        a = nu * stiffness(dx, field="u") + nu * N + divergence(dx, by_parts=True) + mean_constraint(dx) \
            - (beta / nu) * stiffness(dx, field="p", h_power=2)
        if gamma_u > 0:
            a = a + nu * gamma_u * face_jump_penalty(dg, h_power=1, field="u")
        if gamma_p > 0:
            a = a - (gamma_p / nu) * face_jump_penalty(dg, h_power=3, field="p")
        K = assemble(a, W)
        b = assemble(load(f, dx, field="u") + nu * N.load + normal_data * ds, W)
        schur = (1 / nu) * mass(dx) + (beta / nu) * stiffness(dx, h_power=2)
        if gamma_p > 0:
            schur = schur + (gamma_p / nu) * face_jump_penalty(dg, h_power=3)
        S = assemble(schur, V)
    with t("solve"):
        x, info = solve(K, b, method=solver, space=W, primal="u", schur={"p": S}, indefinite_hint=a.indefinite_hint)
        u, p, _ = W.split(x)
        U = W["u"].nodal(u)
    with t("errors"):
        mean = float(np.sum(assemble(load(PRESSURE, dx), V))) / dx.size
        l2u, h1u = l2_h1_errors(V, U, lambda y: (VELOCITY(y), VELOCITY_GRADIENT(y)), dx)
        rec = {
            "h": V.h,
            "dofs": int(W.n_dofs),
            "l2_error_velocity": l2u,
            "h1_error_velocity": h1u,
            "l2_error_pressure": l2_error(V, p, lambda y: PRESSURE(y) - mean, dx),
            "volume": dx.size,
            "solver": info.method,
            "solver_iterations": info.iterations,
        }
    finish_record(rec, cut, W, notes, t)
    rec["fields"] = LazyFields(lambda: {"domain": V.elements.to_pyvista(u_h=U, p_h=p, u_exact=VELOCITY(V.dof_points)),
                                        "boundary": cut.to_pyvista()})
    return rec
