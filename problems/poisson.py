"""Fictitious-domain Poisson problem: symmetric Nitsche and ghost penalty (Burman-Hansbo; docs/math.md §8).

-Lap u = f in Omega = {phi < 0}, u = g on its boundary Gamma.  Find u_h in V_h^NEG (P1 on the tets
that meet Omega_h) with, for all v,

    (grad u, grad v)_{Omega_h} - (n . grad u, v)_Gamma - (u, n . grad v)_Gamma + (gamma / h) (u, v)_Gamma
        + gamma_g sum_{F in G_NEG} h_F ([n_F . grad u], [n_F . grad v])_F
    = (f, v)_{Omega_h} - (g, n . grad v)_Gamma + (gamma / h) (g, v)_Gamma.

Manufactured solution (smooth, not a polynomial): u = sin(pi x / 2) cos(pi y / 3) exp(z / 2), so
-Lap u = (pi^2/4 + pi^2/9 - 1/4) u; g = u on Gamma_h.  The volume load uses quadrature of degree 2
(four points per tet), enough for the O(h^2) of P1; the errors use degree 4.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.norms import l2_h1_errors
from cutfem.fem.forms import assemble
from cutfem.fem.terms import face_jump_penalty, load, nitsche, stiffness
from cutfem.jit import parallel_kernel
from cutfem.geometry.markers import NEG
from cutfem.runs.registry import H_BACKGROUND, LazyFields, Param, register
from cutfem.runs.runner import Timer
from cutfem.solvers.solve import solve
from cutfem.fem.spaces import CutSpace

from .common import finish_record, DOMAIN_PARAMS, ORDER_PARAM, BULK_BYTES_PER_TET, SHAPE_PARAMS, SOLVER_PARAM, background_for, check_bulk_memory, check_ghost_penalty, check_nitsche_penalty, levelset_for, value_and_gradient

_A, _B, _C = np.pi / 2, np.pi / 3, 0.5


@parallel_kernel
def _u_and_gradient(x, u, grad):
    """u and, when ``grad`` has rows, grad u at the points x (n, 3)."""
    with_grad = grad.shape[0] > 0
    for i in prange(x.shape[0]):
        ax, by = _A * x[i, 0], _B * x[i, 1]
        s, e = math.sin(ax), math.exp(_C * x[i, 2])
        ce = math.cos(by) * e
        u[i] = s * ce
        if with_grad:
            grad[i, 0] = _A * math.cos(ax) * ce
            grad[i, 1] = -_B * s * math.sin(by) * e
            grad[i, 2] = _C * u[i]


def exact_u(x):
    """u = sin(a x) cos(b y) exp(c z), a = pi/2, b = pi/3, c = 1/2, at the points x (..., 3).

    The loads evaluate it at every quadrature point (120 million at spacing 0.01), so it runs as one
    compiled loop on all cores (:func:`exact_solution` without the gradient): 0.20 s against numpy's
    0.41-0.46 s for 20 million points on the 2-core machine.  Equal to the numpy expression to an
    ulp or two (libm and numpy compute sin and cos by different routines)."""
    return value_and_gradient(_u_and_gradient, x, gradient=False)[0]


def exact_solution(x):
    """(u, grad u) at the points x (..., 3) (see :func:`exact_u`): each of the five factors
    sin(a x), cos(a x), cos(b y), sin(b y), exp(c z) evaluated once for both.

    The errors evaluate it at every quadrature point (238 million at 2.7 million unknowns), so it
    runs as one compiled loop over the points (on all cores): the L2 and H1 errors took 10.2-11.6 s there against
    15.2-16.9 s for the same expression in numpy (its passes over (m, q) temporaries and strided
    coordinate views), most of what remains being libm's four sines and cosines a point."""
    return value_and_gradient(_u_and_gradient, x)


def measures(cut):
    """(dx over Omega_h, ds over Gamma_h, dF over the ghost facets of NEG): the problem's measures,
    made here alone (a lifted geometry changes them here)."""
    return cut.dx(NEG), cut.ds(), cut.dF(cut.ghost_facets(NEG))


def source(x):
    """f = -Lap u = (a^2 + b^2 - c^2) u."""
    return (_A**2 + _B**2 - _C**2) * exact_u(x)


#: the default ghost penalty gamma_g of each order (:func:`poisson_cut`'s docstring says why 0.01 at order 2)
GHOST_PENALTY = {1: 0.1, 2: 0.01}

#: the record entries of poisson-cut (saved in the JSON of a run)
DEFINITIONS = {
    "h": H_BACKGROUND,
    "l2_error": "||u_h - u||_L2(Omega_h) over the cut volume Omega_h = {phi_h < 0} (degree-4 quadrature on its whole tets and cut parts)",
    "h1_error": "||grad u_h - grad u||_L2(Omega_h), as l2_error",
}


@register(
    "poisson-cut",
    summary="fictitious-domain Poisson -Lap u = f in {phi < 0}, Nitsche on the cut boundary, ghost penalty (docs/math.md §8)",
    levels=[0.2, 0.1, 0.05, 0.025],
    level_name="spacing",
    definitions=DEFINITIONS,
    params=[
        *DOMAIN_PARAMS,
        Param("gamma", float, 10.0, "Nitsche penalty gamma (times order^2 in the form; a warning above 1e3)", positive=True),
        Param("gamma_g", float, None, "ghost penalty gamma_g (default 0.1 at order 1, 0.01 at order 2; meaningful in [0.005, 1]: "
              "a warning above 1, refused above 1e6)", minimum=0),
        ORDER_PARAM,
        SOLVER_PARAM,
        *SHAPE_PARAMS,
    ],
)
def poisson_cut(spacing, surface, background, box, gamma, gamma_g, solver, R, r, radius, axes, order=1):
    """One level of the fictitious-domain Poisson problem.  ``gamma_g`` and ``gamma`` are checked
    first (:func:`~cutfem.problems.common.check_ghost_penalty`, :func:`~cutfem.problems.common.check_nitsche_penalty`);
    their warnings go into the record's ``"warnings"``.  ``order`` 2: P2 fields, every term by
    quadrature of degree 4 (the load 4, the errors 6), the Nitsche penalty gamma k^2 = 4 gamma (at
    gamma 10 the P2 matrix is indefinite) and the ghost penalty of order 2 (the jumps of the first
    and second normal derivatives, docs/math.md §18), on Omega_h lifted by Theta_h (§17).

    ``gamma_g`` defaults to :data:`GHOST_PENALTY` of the order: 0.1 at order 1, 0.01 at order 2.  At
    order 2 the penalty of the second-derivative jumps, gamma_g h_F^3 / 4, dominates the consistency
    error: gamma_g 0.1 gives L2 errors 1.7, 1.4, 1.2 times those of 0.01 at spacings 0.2, 0.1, 0.05, and a
    condition number of the scaled matrix 2.4 times as large (max over 20 shifted balls at spacing
    0.2: 1.2e4 against 6.0e3).  Below 0.01 the Nitsche bound of gamma 40 is lost for some cuts (one
    of those 20 balls indefinite at 0.005), so 0.01 is the smallest weight with margin."""
    if gamma_g is None:
        gamma_g = GHOST_PENALTY[order]
    notes = check_ghost_penalty(gamma_g) + check_nitsche_penalty(gamma)
    t = Timer()
    with t("geometry"):
        phi = levelset_for(surface, R, r, radius, axes)
        bg = background_for(phi, spacing, background, box)
        check_bulk_memory(bg, phi, (NEG,), BULK_BYTES_PER_TET["poisson-cut"], spacing)
        cut = cut_mesh(bg, phi, order=order)  # order 2: Omega_h and Gamma_h lifted by Theta_h (math.md §17)
        V = CutSpace(cut, NEG, order=order)
        dx, ds, ghost = measures(cut)
    with t("assembly"):
        # gamma's one home: the matrix, the load and the advice of the form; times k^2 at order k, the
        # growth of the inverse estimate ||n . grad v||_Gamma <= C k^2 h^-1/2 ||grad v|| of degree-k polynomials
        N = nitsche(ds, gamma * order**2, g=exact_u)
        a = stiffness(dx) + N
        if gamma_g > 0:
            a = a + gamma_g * face_jump_penalty(ghost, h_power=1)
        K = assemble(a, V)
        b = assemble(load(source, dx, degree=2) + N.load, V)
    # order 2: the multigrid's coarse spaces also hold (phi)_+ v, the functions outside Omega_h that
    # only the ghost penalty sees and the P1 coarse space misses (cutfem.solvers.multigrid.augmented_hierarchy)
    multigrid = None if order == 1 else {"augment": np.maximum(phi.value(V.dof_points), 0.0), "coarse_size": 400}
    with t("solve"):
        u, info = solve(K, b, method=solver, space=V, indefinite_hint=a.indefinite_hint, multigrid=multigrid)
    with t("errors"):
        rec = {
            "h": V.h,
            "dofs": int(V.n_dofs),
            **dict(zip(("l2_error", "h1_error"), l2_h1_errors(V, u, exact_solution, dx))),
            "volume": dx.size,
            "gamma_g": gamma_g,  # the one used (the parameter's default, None, is the order's)
            "solver": info.method,
            "solver_iterations": info.iterations,
        }
    finish_record(rec, cut, V, notes, t)
    nodes = V.elements.n_nodes  # VTK: the values at the vertices (the first dofs, at either order)
    rec["fields"] = LazyFields(lambda: {"domain": V.elements.to_pyvista(u_h=u[:nodes], u_exact=exact_u(V.dof_points[:nodes])),
                                        "boundary": cut.to_pyvista()})
    return rec
