"""Compressible linear elasticity in a cut domain: Nitsche and a ghost penalty (docs/math.md §14).

-div sigma(u) = f in Omega = {phi < 0}, u = g on Gamma, sigma(u) = 2 mu eps(u) + lam (div u) I.
Find u_h in [V_h^NEG]^3 (:class:`~cutfem.fem.spaces.VectorSpace`) with, for all v,

    (2 mu eps(u), eps(v)) + (lam div u, div v) - (sigma(u) n, v)_Gamma - (u, sigma(v) n)_Gamma
        + (2 mu + lam) gamma / h (u, v)_Gamma + (2 mu + lam) gamma_g sum_F h_F ([d_n u], [d_n v])_F
    = (f, v) - (g, sigma(v) n)_Gamma + (2 mu + lam) gamma / h (g, v)_Gamma,

solved by CG with the geometric multigrid (three copies of the scalar hierarchy).  Manufactured
displacement (cf.Exact): u = (sin x e^{y/2}, z cos y, x y z + sin z), f = -div sigma(u) derived
symbolically.  Expected L2 O(h^2), H1 O(h) for moderate lam / mu; P1 locks as lam / mu grows (the
constant of the estimate grows with lam): the record keeps the ratio, and the error of a large
ratio is reported as it is, not hidden.
"""

from __future__ import annotations

from cutfem.fem.elasticity import elasticity, elasticity_nitsche
from cutfem.fem.exact import Exact
from cutfem.fem.forms import assemble
from cutfem.fem.norms import l2_h1_errors
from cutfem.fem.spaces import CutSpace, VectorSpace
from cutfem.fem.terms import face_jump_penalty, load
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import NEG
from cutfem.runs.registry import H_BACKGROUND, LazyFields, Param, ProblemError, register
from cutfem.runs.runner import Timer
from cutfem.solvers.solve import solve

from .common import (finish_record, DOMAIN_PARAMS, BULK_BYTES_PER_TET, SHAPE_PARAMS, SOLVER_PARAM, background_for, check_bulk_memory,
                     check_ghost_penalty, check_nitsche_penalty, levelset_for)

DISPLACEMENT = Exact(["sin(x) * exp(y / 2)", "cos(y) * z", "x * y * z + sin(z)"])
GRADIENT = DISPLACEMENT.grad

DEFINITIONS = {
    "h": H_BACKGROUND,
    "dofs": "unknowns: 3 displacement components on the nodes of the tets of NEG",
    "l2_error": "||u_h - u||_L2(Omega_h) of the displacement (degree-4 quadrature on the whole tets and cut parts)",
    "h1_error": "||grad u_h - grad u||_L2(Omega_h)",
}


def load_of(mu: float, lam: float) -> Exact:
    """f = -div sigma(u) of the manufactured displacement."""
    return -(2 * mu * DISPLACEMENT.sym_grad + lam * DISPLACEMENT.div * Exact.identity()).div


@register(
    "elasticity-cut",
    summary="compressible linear elasticity in {phi < 0}, one vector field, Nitsche and a ghost penalty by 2 mu + lam (docs/math.md §14)",
    levels=[0.2, 0.1, 0.05, 0.025],
    level_name="spacing",
    definitions=DEFINITIONS,
    params=[
        *DOMAIN_PARAMS,
        Param("mu", float, 1.0, "shear modulus mu", positive=True),
        Param("lam", float, 2.0, "Lame's first parameter lam (>= 0; P1 locks as lam / mu grows)", minimum=0),
        Param("gamma", float, 10.0, "Nitsche penalty gamma (times 2 mu + lam)", positive=True),
        Param("gamma_g", float, 0.1, "ghost penalty gamma_g (times 2 mu + lam)", minimum=0),
        SOLVER_PARAM,
        *SHAPE_PARAMS,
    ],
)
def elasticity_cut(spacing, surface, background, box, mu, lam, gamma, gamma_g, solver, R, r, radius, axes):
    """One level of cut linear elasticity."""
    if not lam >= 0:
        raise ProblemError(f"--lam must be >= 0 (compressible elasticity), got {lam}")
    notes = check_ghost_penalty(gamma_g) + check_nitsche_penalty(gamma)
    t = Timer()
    with t("geometry"):
        phi = levelset_for(surface, R, r, radius, axes)
        bg = background_for(phi, spacing, background, box)
        check_bulk_memory(bg, phi, (NEG,), BULK_BYTES_PER_TET["elasticity-cut"], spacing)
        cut = cut_mesh(bg, phi)
        V = CutSpace(cut, NEG)
        W = VectorSpace(V)
        dx, ds = cut.dx(NEG), cut.ds()
    with t("assembly"):
        N = elasticity_nitsche(ds, mu, lam, gamma, g=DISPLACEMENT)
        a = elasticity(dx, mu, lam) + N
        if gamma_g > 0:
            a = a + (2 * mu + lam) * gamma_g * face_jump_penalty(cut.dF(cut.ghost_facets(NEG)), h_power=1)
        K = assemble(a, W)
        b = assemble(load(load_of(mu, lam), dx) + N.load, W)
    with t("solve"):
        u, info = solve(K, b, method=solver, space=W, indefinite_hint=a.indefinite_hint)
    with t("errors"):
        l2, h1 = l2_h1_errors(W, u, lambda x: (DISPLACEMENT(x), GRADIENT(x)), dx)
        rec = {"h": W.h, "dofs": int(W.n_dofs), "l2_error": l2, "h1_error": h1, "lam_over_mu": lam / mu,
               "volume": dx.size, "solver": info.method, "solver_iterations": info.iterations}
    finish_record(rec, cut, W, notes, t)
    rec["fields"] = LazyFields(lambda: {"domain": V.elements.to_pyvista(u_h=W.nodal(u), u_exact=DISPLACEMENT(V.dof_points)),
                                        "boundary": cut.to_pyvista()})
    return rec
