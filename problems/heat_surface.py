"""The heat equation on a stationary cut surface: TraceFEM in space, theta-scheme in time
(docs/math.md §11).

u_t - Lap_Gamma u = f on the sphere Gamma of radius R, u(0) = u_0.  With the P1 trace space on the cut
tets, the stabilized mass M_h = M + tau_N s_{+1} and stiffness A_h = A + tau_N s_{-1}, where
s_a(u, v) = sum_T h_T^a (n_h . grad u, n_h . grad v)_T is the normal-gradient term (its h^1 version
scales like the surface mass, its h^-1 version like the surface stiffness), each step solves

    (M_h + theta dt A_h) u^n = (M_h - (1 - theta) dt A_h) u^{n-1} + dt (theta F^n + (1 - theta) F^{n-1}),

F^n = (f(t_n)^e, v)_{Gamma_h}, here exp(-t_n) G with G assembled once (the source below separates).  theta = 1 (backward Euler) with dt = c h^2 and theta = 1/2
(Crank-Nicolson) with dt = c h, h the background spacing and c = ``dt_scale``, both O(h^2) in L2.
The matrix is factorized once.  u_0 is the nodal interpolant of the normal extension u_0 o p.

Manufactured solution (smooth, not a polynomial): u = exp(-t) U(p(x)), U = exp(d . x), d = (0.6, 0.3, -0.4);
f = u_t - Lap_Gamma u = -exp(-t) (U + Lap_Gamma U) with
Lap_Gamma U = U (|d|^2 - (d . n)^2 - (2 / R) d . n) on the sphere (n = x / R, H = 2 / R).
"""

from __future__ import annotations

import numpy as np

from cutfem.cut import cut_mesh
from cutfem.errors import l2_error
from cutfem.forms import assemble, load, mass, normal_gradient_penalty, tangential_stiffness
from cutfem.levelset import Sphere
from cutfem.markers import CUT
from cutfem.registry import Param, ProblemError, register
from cutfem.solve import DirectSolver
from cutfem.spaces import CutP1Space

from .common import Timer, background_for, cut_record

_D = np.array([0.6, 0.3, -0.4])


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
    params=[
        Param("theta", float, 1.0, "theta of the time scheme: 1 backward Euler (dt = c h^2), 0.5 Crank-Nicolson (dt = c h)", choices=(1.0, 0.5)),
        Param("dt_scale", float, 1.0, "c in dt = c h^2 (theta = 1) or dt = c h (theta = 1/2)", minimum=0),
        Param("final_time", float, 0.5, "final time T", minimum=0),
        Param("tau_n", float, 1.0, "normal-gradient stabilization tau_N", minimum=0),
        Param("radius", float, 1.0, "radius of the sphere", minimum=0),
        Param("box", str, None, "background box x0,y0,z0,x1,y1,z1 (default: the sphere's box grown by 0.1)"),
    ],
)
def heat_surface_cut(spacing, theta, dt_scale, final_time, tau_n, radius, box):
    """One level: the L2(S_h) error at the final time."""
    if not (dt_scale > 0 and final_time > 0):
        raise ProblemError("--dt-scale and --final-time must be positive")
    sol = HeatSolution(radius)
    t = Timer()
    with t("geometry"):
        phi = Sphere(radius)
        cut = cut_mesh(background_for(phi, spacing, "structured", box), phi)
        V = CutP1Space(cut, CUT)
        ds = cut.ds()
    with t("assembly"):
        M = assemble(mass(ds) + tau_n * normal_gradient_penalty(cut.dx(CUT), h_power=1), V)
        A = assemble(tangential_stiffness(ds) + tau_n * normal_gradient_penalty(cut.dx(CUT), h_power=-1), V)
        dt_target = dt_scale * (spacing**2 if theta == 1.0 else spacing)
        steps = max(1, int(np.ceil(final_time / dt_target - 1e-9)))
        dt = final_time / steps
        solver = DirectSolver((M + theta * dt * A).tocsr())
        explicit = (M - (1.0 - theta) * dt * A).tocsr()
    with t("time steps"):
        u = sol.u(0.0)(V.dof_points)
        G = assemble(load(sol.source_profile, ds), V)  # f = exp(-t) g: F^n = exp(-t_n) G
        for n in range(1, steps + 1):  # time steps, not elements
            F = (theta * np.exp(-n * dt) + (1.0 - theta) * np.exp(-(n - 1) * dt)) * G
            u = solver.solve(explicit @ u + dt * F)
    with t("errors"):
        rec = {
            "h": V.h,
            "dofs": int(V.n_dofs),
            "time_steps": steps,
            "dt": dt,
            "l2_error": l2_error(V, u, sol.u(final_time)),
            "area": cut.area,
        }
    rec.update(cut_record(cut))
    rec["time"] = dict(t)
    return rec
