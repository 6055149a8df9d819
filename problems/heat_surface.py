"""The heat equation on a stationary cut surface: TraceFEM in space, theta-scheme in time
(docs/math.md §11).

u_t - Lap_Gamma u = f on the sphere Gamma of radius R, u(0) = u_0.  With the P1 trace space on the cut
tets, the stabilized mass M_h = M + tau_N s_{+1} and stiffness A_h = A + tau_N s_{-1}, where
s_a(u, v) = sum_T h_T^a (n_h . grad u, n_h . grad v)_T is the normal-gradient term (its h^1 version
scales like the surface mass, its h^-1 version like the surface stiffness), each step solves

    (M_h + theta dt A_h) u^n = (M_h - (1 - theta) dt A_h) u^{n-1} + dt (theta F^n + (1 - theta) F^{n-1}),

F^n = (f(t_n)^e, v)_{Gamma_h}, here exp(-t_n) G with G assembled once (the source below separates).  theta = 1 (backward Euler) with dt = c h^2 and theta = 1/2
(Crank-Nicolson) with dt = c h, h the background spacing and c = ``dt_scale``, both O(h^2) in L2.
The steps are uniform and end exactly at the final time T: N = ceil(T / (c h^p)) steps of dt = T / N
(:func:`time_steps`, which refuses a count that would take hours).
u_0 is the nodal interpolant of the normal extension u_0 o p.

The steps' solver (``solver``): ``direct`` factorizes M_h + theta dt A_h once and solves with the
factor at every step; ``cg-jacobi`` builds CG with the inverse diagonal once and starts each step
from the polynomial through the last three solutions, extrapolated to the new time (the first
steps from the ones there are), to the relative residual :data:`STEP_TOL`; ``cg-mg`` is the same
with the geometric multigrid (:class:`cutfem.solvers.multigrid.GeometricMultigrid` on the nested lattices of
the box); ``auto`` is direct up to :data:`STEP_DIRECT_LIMIT` unknowns, above it cg-jacobi for
backward Euler and cg-mg for Crank-Nicolson.  Why Jacobi suffices for backward Euler: with dt = c h^2 the matrix M_h + dt A_h is spectrally equivalent to the mass M_h
(A_h <= C h^-2 M_h), so CG's iterations do not grow with 1/h; and the solution is smooth in time,
so the extrapolated start leaves CG an error of O(dt^3) to remove.  Backward Euler, measured
(2026-12-03, ``python -m cutfem.studies.time_stepping --full`` gives the same table for both
schemes and all three solvers; iterations a step on average, the final L2 error against the
factor's):

=======  =========  =====  ==========  ==========  ======================
spacing  unknowns   steps  iterations  L2 error    time of the steps (s)
                                       relative    cg-jacobi / direct
                                       change
=======  =========  =====  ==========  ==========  ======================
0.1      2 932      50     30.9        8e-10       0.26 / 0.02
0.05     11 824     200    21.0        2e-9        1.09 / 0.47
0.025    47 464     800    12.4        6e-9        7.3 / 10.6 (+0.7 factor)
0.0125   190 060    3 200  5.3         1e-6        58 / 229 (+6.8 factor)
=======  =========  =====  ==========  ==========  ======================

(at spacing 0.025, 60 iterations a step from zero and 44 from the previous solution.)
Crank-Nicolson's dt = c h makes the matrix stiffness-like (condition ~ 1/h): Jacobi needs 87, 113
and 150 iterations a step at spacings 0.1, 0.05 and 0.025, the multigrid 12 at 0.025 and 0.0125
(0.80 s for the 20 steps at 0.025 against 1.04 s factorized; 5.2 s for the 40 steps at 0.0125
against 10.8 s, the final L2 errors equal to 1e-10 relative).

Manufactured solution (smooth, not a polynomial): u = exp(-t) U(p(x)), U = exp(d . x), d = (0.6, 0.3, -0.4);
f = u_t - Lap_Gamma u = -exp(-t) (U + Lap_Gamma U) with
Lap_Gamma U = U (|d|^2 - (d . n)^2 - (2 / R) d . n) on the sphere (n = x / R, H = 2 / R).
"""

from __future__ import annotations

import math

import numpy as np

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.norms import l2_error
from cutfem.fem.forms import assemble
from cutfem.fem.terms import load, mass, normal_gradient_penalty, tangential_stiffness
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.markers import CUT
from cutfem.runs.registry import H_BACKGROUND, LazyFields, Param, ProblemError, register
from cutfem.runs.runner import Timer
from cutfem.solvers.krylov import CGSolver
from cutfem.solvers.solve import DirectSolver, multigrid_hierarchy
from cutfem.fem.spaces import CutSpace

from .common import finish_record, background_for, check_cut_memory, check_normal_stabilization, check_resolution, with_point_data
from cutfem.solvers import sparse_kernels

_D = np.array([0.6, 0.3, -0.4])

#: relative residual ||S u - b|| / ||b|| of every step's CG solve (``solver="cg-jacobi"``).  The
#: schemes do not amplify the steps' algebraic errors, but over many steps they add up: at spacing
#: 0.0125 (3 200 steps) 1e-10 moved the final L2 error by 1.1e-4 relative (1.8 iterations a step),
#: 1e-12 by 1e-6 (5.3 iterations a step)
STEP_TOL = 1e-12

#: ``solver="auto"`` factorizes up to this many unknowns (the break-evens of the module docstring lie
#: between 11 824 and 47 464)
STEP_DIRECT_LIMIT = 30_000


#: a level takes at most this many time steps ...
MAX_STEPS = 1_000_000

#: ... and at most this many unknowns times steps: ten times the 6e8 of the finest level measured
#: (spacing 0.0125, 3 200 steps; 1 to 4 minutes), where a step costs about 0.1 microseconds an unknown
MAX_STEP_UNKNOWNS = 10**10


#: the longest final time, in units of the fastest time scale of the mesh (the largest row sum of
#: |A_h| over that of M_h 1): see :func:`check_final_time`
MAX_FINAL_TIME_SCALES = 1e10


def check_final_time(M, A, final_time):
    """Refuse (ProblemError) a final time T after which rounding has changed the integral of u_h
    by more than about 1e-6 of itself, naming the longest T that passes.

    Only M_h sees the constants (A_h 1 = 0); in M_h + theta dt A_h (and M_h - (1 - theta) dt A_h)
    a step keeps them to about eps dt k, k = max row sum |A_h| / max (M_h 1) (about 9 h^-2 on the
    unit sphere, h the spacing: 58 at 0.4, 834 at 0.1), and the N = T / dt steps add these up to eps T k, whatever dt: measured, at spacing 0.4
    (k = 58) backward Euler to T = 1e12 in 7 steps ends 2e-3 away from the constant of the initial
    integral, which T = 1e4 gives to 1e-8.  Refused above
    :data:`MAX_FINAL_TIME_SCALES` = T k, where the loss is about 1e-6."""
    k = abs(A).sum(axis=1).max() / (M @ np.ones(M.shape[0])).max()
    if final_time * k > MAX_FINAL_TIME_SCALES:
        longest = MAX_FINAL_TIME_SCALES / k * (1 - 1e-3)  # 4 digits, rounded down
        raise ProblemError(
            f"--final-time {final_time:g} is {final_time * k:.2g} times the fastest time scale of this mesh, 1 / {k:.3g} "
            f"(largest row sum of |A_h| over that of M_h 1): the steps' rounding adds up to about {2.2e-16 * final_time * k:.1g} "
            f"of the integral of u_h (M_h, the only part the constants see, keeps about eps dt {k:.3g} a step); "
            f"shorten --final-time to at most {longest:.4g} (exp(-T) of the solution has long vanished)"
        )


def time_steps(final_time, dt_scale, spacing, theta, dofs):
    """(N, dt): the N uniform steps of the level, which end exactly at the final time T.

    The step asked for is dt_max = c h^2 (theta = 1) or c h (theta = 1/2), c = ``dt_scale``, h =
    ``spacing``; the level takes N = ceil(T / dt_max) steps (a ratio within 1e-9 of an integer
    counts as that integer) of dt = T / N <= dt_max: a T that is not a multiple of dt_max shortens
    every step alike, never the final time, and a dt_max beyond T gives the single step dt = T.

    Raises ProblemError when N exceeds :data:`MAX_STEPS` or N * ``dofs`` exceeds
    :data:`MAX_STEP_UNKNOWNS` (hours of steps; also a dt_max lost to underflow, T / dt_max = inf),
    naming the smallest ``dt_scale`` that runs."""
    power = 2 if theta == 1.0 else 1
    dt_max = dt_scale * spacing**power
    ratio = final_time / dt_max if dt_max > 0 else math.inf
    limit = max(1, min(MAX_STEPS, MAX_STEP_UNKNOWNS // max(int(dofs), 1)))
    if ratio - 1e-9 > limit:
        need = final_time / (limit * spacing**power) * (1 + 1e-3)  # 4 digits below, rounded up
        raise ProblemError(
            f"--dt-scale {dt_scale:g} and --final-time {final_time:g} at spacing {spacing:g} ask for {ratio:.3g} time "
            f"steps of {dt_max:.3g} on {dofs} unknowns, more than the {limit} a level takes (at most {MAX_STEPS} steps "
            f"and {MAX_STEP_UNKNOWNS:.0e} unknowns x steps); raise --dt-scale to at least {need:.4g} or shorten --final-time"
        )
    steps = max(1, math.ceil(ratio - 1e-9))
    return steps, final_time / steps


def theta_steps(M, A, u0, G, amplitude, final_time, steps, theta, step):
    """u^N, and the solver's iterations summed over the steps, of the theta-scheme with N = ``steps``
    uniform steps dt = T / N from u^0 = ``u0`` ((n,)) to t_N = T exactly (t_n = n T / N):

        (M + theta dt A) u^n = (M - (1 - theta) dt A) u^{n-1} + dt (theta a(t_n) + (1 - theta) a(t_{n-1})) G,

    the load F(t) = a(t) G of a separable source, a = ``amplitude`` (a function of t).  ``step(b,
    history)`` -> (u^n, iterations) solves with M + theta dt A, ``history`` the last up to three
    solutions, oldest first (for :func:`extrapolated`).  With A 1 = 0 (a closed surface) and
    s(., 1) = 0 in M, 1^T M u^n = 1^T M u^{n-1} + dt (theta a(t_n) + (1 - theta) a(t_{n-1})) 1^T G
    exactly: the integral of u_h over S_h follows the source; for G = 0 it is conserved and the
    energy u^T M u does not grow (theta >= 1/2, M and A symmetric positive semidefinite)."""
    dt = final_time / steps
    explicit = (M - (1.0 - theta) * dt * A).tocsr()
    u = np.asarray(u0, dtype=float)
    history, iterations = [u], 0
    b = np.empty((len(u), 1))
    for n in range(1, steps + 1):  # time steps, not elements
        t_n, t_before = final_time * n / steps, final_time * (n - 1) / steps
        weight = dt * (theta * amplitude(t_n) + (1.0 - theta) * amplitude(t_before))
        # b = explicit u + dt F^n (the compiled product on both cores: 1 ms against scipy's 3 ms at 190k unknowns)
        sparse_kernels.matmul(explicit, u.reshape(-1, 1), out=b)
        b[:, 0] += weight * G
        u, its = step(b[:, 0], history)
        iterations += its
        history = [*history[-2:], u]
    return u, iterations


def extrapolated(history):
    """The polynomial in time through the solutions ``history`` (the last up to three, oldest
    first, at equal steps), evaluated one step on: u, 2 u - u_1, or 3 u - 3 u_1 + u_2 (u the
    newest)."""
    if len(history) == 1:
        return history[-1].copy()
    if len(history) == 2:
        return 2.0 * history[-1] - history[-2]
    return 3.0 * (history[-1] - history[-2]) + history[-3]


class HeatSolution:
    """u = exp(-t) exp(d . p(x)) on the sphere of radius R, and its source term."""

    def __init__(self, R):
        self.R = float(R)

    def closest_point(self, x):
        return self.R * x / np.linalg.norm(x, axis=-1, keepdims=True)

    def u(self, t):
        return lambda x: np.exp(-t) * np.exp(self.closest_point(x) @ _D)

    def source_profile(self, x):
        """g with f(x, t) = exp(-t) g(x): g = -(U + Lap_Gamma U) at the closest point."""
        p = self.closest_point(x)
        U, dn = np.exp(p @ _D), (p @ _D) / self.R
        return -(U + U * (_D @ _D - dn**2 - (2.0 / self.R) * dn))


@register(
    "heat-surface-cut",
    summary="surface heat equation on a cut sphere, TraceFEM + theta-scheme (docs/math.md §11)",
    levels=[0.4, 0.2, 0.1, 0.05],
    level_name="spacing",
    definitions={"h": H_BACKGROUND, "l2_error": "||u_h(T) - u(T)^e||_L2(S_h) at the final time T (the record's final_time, reached in "
                             "time_steps steps of dt), u^e the normal extension of the exact solution"},
    params=[
        Param("theta", float, 1.0, "theta of the time scheme: 1 backward Euler (dt = c h^2), 0.5 Crank-Nicolson (dt = c h)", choices=(1.0, 0.5)),
        Param("dt_scale", float, 1.0, "c in dt_max = c h^2 (theta = 1) or c h (theta = 1/2), h the spacing: the level takes "
              "N = ceil(T / dt_max) steps of dt = T / N, which end exactly at T", minimum=0),
        Param("final_time", float, 0.5, "final time T", minimum=0),
        Param("tau_n", float, 1.0, "normal-gradient stabilization tau_N (at 0, phi_h, zero on S_h, is a null vector of "
              "the steps' matrix: direct and cg-mg refuse it, cg-jacobi never meets it; a warning above 100, refused below 1e-8 "
              "and above 1e6)", minimum=0),
        Param("radius", float, 1.0, "radius of the sphere", positive=True),
        Param("box", str, None, "background box x0,y0,z0,x1,y1,z1 (default: the sphere's box grown by 0.1)"),
        Param("solver", str, "auto", "the steps' solver: direct (one factorization), cg-jacobi or cg-mg (CG from the "
              f"extrapolated solutions), auto (direct up to {STEP_DIRECT_LIMIT} unknowns, then cg-jacobi for backward "
              "Euler, cg-mg for Crank-Nicolson)", choices=("auto", "direct", "cg-jacobi", "cg-mg")),
    ],
)
def heat_surface_cut(spacing, theta, dt_scale, final_time, tau_n, radius, box, solver):
    """One level: the L2(S_h) error at the final time; the fields (for ``--vtk``) are u_h and the
    exact u at the final time on the surface S_h."""
    if not final_time > 0:
        raise ProblemError(f"--final-time {final_time:g}: the final time must be positive (default 0.5)")
    if not dt_scale > 0:
        raise ProblemError(f"--dt-scale {dt_scale:g}: the step dt_max = c h^2 or c h must be positive (default 1)")
    notes = check_normal_stabilization(tau_n, 1.0, spacing)  # h^1 beside the mass, h^-1 beside the stiffness: weight tau_N
    sol = HeatSolution(radius)
    t = Timer()
    with t("geometry"):
        phi = Sphere(radius)
        cut = cut_mesh(background_for(phi, spacing, "structured", box), phi)
        check_resolution(cut, phi, spacing)  # before the closest point is taken at a node near the centre
        check_cut_memory(cut, spacing=spacing)
        V = CutSpace(cut, CUT)
        ds = cut.ds()
        steps, dt = time_steps(final_time, dt_scale, spacing, theta, V.n_dofs)
    with t("assembly"):
        M = assemble(mass(ds) + tau_n * normal_gradient_penalty(cut.dx(CUT), h_power=1), V)
        A = assemble(tangential_stiffness(ds) + tau_n * normal_gradient_penalty(cut.dx(CUT), h_power=-1), V)
        check_final_time(M, A, final_time)
        S = (M + theta * dt * A).tocsr()
        if solver == "auto":
            solver = "direct" if V.n_dofs <= STEP_DIRECT_LIMIT else "cg-jacobi" if theta == 1.0 else "cg-mg"
        # phi_h (zero on S_h) is a null vector of M and A at tau_N = 0: the factor and the multigrid name it
        candidates = {"phi_h": cut.values}
        if solver == "direct":
            factor = DirectSolver(S, kernels=candidates)
            step = lambda b, history: (factor.solve(b), 0)  # noqa: E731
        else:
            cg = CGSolver(S, "jacobi" if solver == "cg-jacobi" else "mg", tol=STEP_TOL, kernels=candidates,
                          prolongations=multigrid_hierarchy(V) if solver == "cg-mg" else None)

            def step(b, history):  # CG from the solutions extrapolated to the new time
                x, info = cg.solve(b, extrapolated(history))
                return x, info.iterations
    with t("time steps"):
        G = assemble(load(sol.source_profile, ds), V)  # f = exp(-t) g: F^n = exp(-t_n) G
        u, iterations = theta_steps(M, A, sol.u(0.0)(V.dof_points), G, lambda t: np.exp(-t), final_time, steps, theta, step)
    with t("errors"):
        rec = {
            "h": V.h,
            "dofs": int(V.n_dofs),
            "time_steps": steps,
            "dt": dt,
            "final_time": final_time,
            "solver": solver,
            "step_iterations": iterations / steps,
            "l2_error": l2_error(V, u, sol.u(final_time)),
            "area": cut.area,
        }
    finish_record(rec, cut, None, notes, t)
    rec["fields"] = LazyFields(lambda: {"surface": with_point_data(
        cut.to_pyvista(), u_h=V.surface_vertex_values(u), u_exact=sol.u(final_time)(cut.vertices))})
    return rec
