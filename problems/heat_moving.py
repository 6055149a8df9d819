"""The heat equation in a moving domain, Eulerian BDF1/BDF2 with a ghost-penalty extension
(Lehrenfeld and Olshanskii, ESAIM: M2AN 53, 2019; docs/math.md §13).

u_t - Lap u = f in Omega(t) = {|x - c(t)| < R}, a ball translating with the velocity w, u = g on its
boundary, t in (0, T].  At t_{n+1} the unknown lives on the tets of the extended domain
{phi(., t_{n+1}) < delta} (:class:`~cutfem.fem.moving.ActiveDomain`), delta = 1.5 k |w| dt for BDF k,
and solves, for all v of that space,

    (a_0 u^{n+1} - sum_j a_j u^{n+1-j}, v)_{Omega^{n+1}} / dt + (grad u^{n+1}, grad v)_{Omega^{n+1}}
        + Nitsche on Gamma^{n+1} (gamma) + gamma_g sum_{F in strip} (h_F + h_F^3 / dt) ([d_n u], [d_n v])_F
    = (f, v)_{Omega^{n+1}} + the Nitsche load of g,

BDF1: a = (1; 1), BDF2: a = (3/2; 2, -1/2) (its first step BDF1), the earlier solutions carried to the
new space by their values at the background nodes (:func:`~cutfem.fem.moving.transfer`).  The
strip facets' penalty extends each solution past the boundary, where the next steps read it.

Manufactured solution u = exp(-t) w(x), w = cos(x) sin(y + 1/2) exp(z/2) (cf.Exact), so f = exp(-t)
(-w - Lap w); the ball of radius 0.5 starts at (-0.25, 0, 0) and moves with w = (0.5, 0, 0) until
T = 0.5.  With dt = h / 2 BDF2's error at T is O(h^2); BDF1 needs dt ~ h^2 for it.
"""

from __future__ import annotations

import numpy as np

from cutfem.fem.exact import Exact
from cutfem.fem.forms import assemble
from cutfem.fem.moving import ActiveDomain, strip_width, transfer
from cutfem.fem.norms import l2_h1_errors
from cutfem.fem.terms import face_jump_penalty, load, mass, nitsche, stiffness
from cutfem.geometry.box import structured_box
from cutfem.geometry.shapes import Sphere
from cutfem.runs.registry import H_BACKGROUND, Param, ProblemError, register
from cutfem.runs.runner import Timer
from cutfem.solvers.solve import solve

from .common import finish_record, SOLVER_PARAM, check_ghost_penalty, check_nitsche_penalty

W = Exact("cos(x) * sin(y + 1/2) * exp(z/2)")
SOURCE = -W - W.laplacian
GRADIENT = W.grad
START, VELOCITY = np.array([-0.25, 0.0, 0.0]), np.array([0.5, 0.0, 0.0])
BOX = ([-1.25, -1.25, -1.25], [1.25, 1.25, 1.25])

#: BDF coefficients: a_0 and the weights of the earlier solutions, newest first
BDF = {1: (1.0, (1.0,)), 2: (1.5, (2.0, -0.5))}

DEFINITIONS = {
    "h": H_BACKGROUND,
    "l2_error": "||u_h(T) - u(T)||_L2(Omega_h(T)) at the final time (degree-4 quadrature)",
    "h1_error": "||grad (u_h(T) - u(T))||_L2(Omega_h(T)) at the final time",
}


def ball(t, radius):
    return Sphere(radius, START + VELOCITY * t)


@register(
    "heat-moving-cut",
    summary="heat equation in a translating ball, Eulerian BDF1/BDF2 with a ghost-penalty extension strip (docs/math.md §13)",
    levels=[0.2, 0.1, 0.05, 0.025],
    level_name="spacing",
    definitions=DEFINITIONS,
    params=[
        Param("order", int, 2, "BDF order: 1 or 2", choices=(1, 2)),
        Param("dt_factor", float, 0.5, "time step dt = dt_factor * h (BDF2), dt_factor * h^2 (BDF1)", positive=True),
        Param("final_time", float, 0.5, "final time T", positive=True),
        Param("radius", float, 0.5, "radius of the ball", positive=True),
        Param("gamma", float, 20.0, "Nitsche penalty gamma", positive=True),
        Param("gamma_g", float, 0.1, "ghost penalty of the extension strip (h_F + h_F^3 / dt)", positive=True),
        SOLVER_PARAM,
    ],
)
def heat_moving_cut(spacing, order, dt_factor, final_time, radius, gamma, gamma_g, solver):
    """One level: BDF steps from t = 0 to ``final_time``, the error at the final time."""
    notes = check_ghost_penalty(gamma_g) + check_nitsche_penalty(gamma)
    t = Timer()
    steps = max(1, int(np.ceil(final_time / (dt_factor * (spacing if order == 2 else spacing**2)))))
    dt = final_time / steps
    delta = strip_width(float(np.linalg.norm(VELOCITY)), dt, order)
    end = START + VELOCITY * final_time
    if np.any(np.abs(np.concatenate([START, end])) + radius + delta >= BOX[1][0] - spacing):
        raise ProblemError(f"--radius {radius:g} and --final-time {final_time:g}: the ball and its strip leave the box "
                           f"[-{BOX[1][0]:g}, {BOX[1][0]:g}]^3 (with a cell of margin); take a smaller radius or final time")
    with t("geometry"):
        background = structured_box(*BOX, spacing=spacing)
        domain = ActiveDomain(background, ball(0.0, radius), delta)
    history = [(domain.space.interpolate(W), domain.space)]
    iterations = 0
    with t("steps"):  # each step: the cut at t_{n+1} and its extension, the assembly, the solve
        for n in range(steps):
            time_new = (n + 1) * dt
            domain = ActiveDomain(background, ball(time_new, radius), delta)
            V, dx = domain.space, domain.dx
            k = 1 if n == 0 else order
            a0, weights = BDF[k]
            decay = np.exp(-time_new)
            N = nitsche(domain.ds, gamma, g=lambda x, decay=decay: decay * W(x))
            a = (a0 / dt) * mass(dx) + stiffness(dx) + N + gamma_g * face_jump_penalty(domain.dF, h_power=1) \
                + (gamma_g / dt) * face_jump_penalty(domain.dF, h_power=3)
            K = assemble(a, V)
            b = assemble(load(lambda x, decay=decay: decay * SOURCE(x), dx) + N.load, V)
            earlier = sum(c * transfer(u, old, V, over=dx) for c, (u, old) in zip(weights, reversed(history[-k:])))
            b += assemble(mass(dx), V) @ (earlier / dt)
            u, info = solve(K, b, method=solver, space=V, indefinite_hint=a.indefinite_hint)
            iterations = max(iterations, info.iterations)
            history = (history + [(u, V)])[-2:]
    u, V = history[-1]
    decay = np.exp(-final_time)
    with t("errors"):
        l2, h1 = l2_h1_errors(V, u, lambda x: (decay * W(x), decay * GRADIENT(x)), domain.dx)
    rec = {
        "h": V.h,
        "dofs": int(V.n_dofs),
        "l2_error": l2,
        "h1_error": h1,
        "steps": steps,
        "dt": dt,
        "strip_width": delta,
        "strip_facets": int(domain.strip_facets.n_facets),
        "solver": info.method,
        "solver_iterations": iterations,
    }
    finish_record(rec, domain.cut, V, notes, t)  # the domain at the final time; active tets: the extended ones
    return rec
