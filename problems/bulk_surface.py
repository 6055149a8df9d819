"""Coupled bulk-surface problem (Burman, Hansbo, Larson, Zahedi; docs/math.md §10).

Bulk u_B in the ball Omega = {|x| < R}, surface u_S on Gamma = its boundary sphere:

    -div(k_B grad u_B) + c_B u_B = f_B in Omega,       k_B n . grad u_B = b_S u_S - b_B u_B on Gamma,
    -div_Gamma(k_S grad_Gamma u_S) + b_S u_S - b_B u_B = f_S on Gamma.

Weighted to a symmetric form (bulk equation times b_B, surface equation times b_S), with u_B in
V_h^NEG (ghost penalty on the ghost faces of NEG) and u_S in V_h^Gamma (the normal-gradient
stabilization on the cut tets, tau_N h^-1 (n_h . grad u_S, n_h . grad v_S) scaled like the surface stiffness):

    b_B (k_B grad u_B, grad v_B)_Omega + b_B c_B (u_B, v_B)_Omega + b_S (k_S grad_Gamma u_S, grad_Gamma v_S)_Gamma
    + (b_S u_S - b_B u_B, b_S v_S - b_B v_B)_Gamma + stabilizations = b_B (f_B, v_B)_Omega + b_S (f_S, v_S)_Gamma.

c_B > 0 is required: with c_B = 0 the solution is unique only up to (c / b_B, c / b_S).

Manufactured solution (smooth, not a polynomial): u_B = exp(d . x) with d = (0.6, 0.3, -0.4), and
u_S fixed by the coupling condition, u_S = (k_B n . grad u_B + b_B u_B) / b_S on Gamma, extended by
U_S(x) = F(d . x), F(s) = e^s (k_B s / R + b_B) / b_S (on Gamma n = x / R, so n . grad u_B = (d . x / R) u_B).
Then f_B = (c_B - k_B |d|^2) u_B and f_S = -k_S Lap_Gamma U_S + b_S U_S - b_B u_B on Gamma, with

    Lap_Gamma U = trace(P Hess U) - H n . grad U = F''(s) (|d|^2 - (d . n)^2) - (2 / R) F'(s) d . n,

for the sphere's H = 2 / R, all at the closest point p(x) = R x / |x|.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.norms import h1_error, l2_error, l2_h1_errors
from cutfem.fem.forms import assemble, bilinear_form
from cutfem.fem.terms import face_jump_penalty, load, mass, normal_gradient_penalty, stiffness, tangential_stiffness
from cutfem.jit import parallel_kernel
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.markers import CUT, NEG
from cutfem.runs.registry import H_BACKGROUND, LazyFields, Param, ProblemError, register
from cutfem.runs.runner import Timer
from cutfem.solvers.solve import solve
from cutfem.fem.spaces import CutSpace, ProductSpace

from .common import finish_record, BULK_BYTES_PER_TET, SOLVER_PARAM, background_for, check_bulk_memory, check_ghost_penalty, check_normal_stabilization, check_resolution, value_and_gradient, with_point_data

_D = np.array([0.6, 0.3, -0.4])


@parallel_kernel
def _exp_and_gradient(x, d, u, grad):
    """u = exp(d . x) and, when ``grad`` has rows, grad u = u d at the points x (n, 3)."""
    with_grad = grad.shape[0] > 0
    for i in prange(x.shape[0]):
        u[i] = math.exp(x[i, 0] * d[0] + x[i, 1] * d[1] + x[i, 2] * d[2])
        if with_grad:
            grad[i, 0], grad[i, 1], grad[i, 2] = u[i] * d[0], u[i] * d[1], u[i] * d[2]


class BulkSurfaceSolution:
    """The manufactured solution above on the sphere of radius R."""

    def __init__(self, R, k_b, k_s, b_b, b_s, c_b):
        self.R, self.k_b, self.k_s, self.b_b, self.b_s, self.c_b = map(float, (R, k_b, k_s, b_b, b_s, c_b))

    def closest_point(self, x):
        return self.R * x / np.linalg.norm(x, axis=-1, keepdims=True)

    def u_bulk(self, x):
        return self.bulk(x, gradient=False)[0]

    def bulk(self, x, gradient=True):
        """(u_B, grad u_B = u_B d) at the points x (..., 3), the exponential once for both, in one
        compiled loop on all cores (the errors evaluate it at every quadrature point: numpy's matrix
        product x @ d and broadcast u d took 0.33 s of the errors at spacing 0.025); grad None
        without ``gradient``."""
        return value_and_gradient(_exp_and_gradient, x, _D, gradient=gradient)

    def f_bulk(self, x):
        return (self.c_b - self.k_b * _D @ _D) * self.u_bulk(x)

    def _F(self, s):
        e, k, R = np.exp(s), self.k_b, self.R
        return e * (k * s / R + self.b_b) / self.b_s, e * (k * s / R + self.b_b + k / R) / self.b_s, e * (k * s / R + self.b_b + 2 * k / R) / self.b_s

    def u_surface(self, x):
        """U_S at the closest point of x."""
        return self._F(self.closest_point(x) @ _D)[0]

    def grad_surface(self, x):
        """grad U_S at the closest point (its tangential part is the surface gradient)."""
        return self._F(self.closest_point(x) @ _D)[1][..., None] * _D

    def f_surface(self, x):
        p = self.closest_point(x)
        s, dn = p @ _D, (p @ _D) / self.R
        F, F1, F2 = self._F(s)
        lap = F2 * (_D @ _D - dn**2) - (2.0 / self.R) * F1 * dn
        return -self.k_s * lap + self.b_s * F - self.b_b * np.exp(s)


#: the record's entries (saved with the JSON)
DEFINITIONS = {
    "h": H_BACKGROUND,
    "dofs": "unknowns of the coupled system, dofs_bulk + dofs_surface: the nodes of the tets of NEG plus the nodes of "
            "the cut tets",
    "l2_error_bulk": "||u_B,h - u_B||_L2(Omega_h), Omega_h the NEG cut volume (degree-4 quadrature on its whole tets and cut parts)",
    "h1_error_bulk": "||grad u_B,h - grad u_B||_L2(Omega_h)",
    "l2_error_surface": "||u_S,h - u_S o p||_L2(Gamma_h), u_S at the closest point p on the sphere (degree-4 quadrature on S_h)",
    "h1_error_surface": "||P_h (grad u_S,h - grad U_S)||_L2(Gamma_h), P_h the tangential projection of Gamma_h, U_S the "
                        "extension of the module docstring",
}


@register(
    "bulk-surface-cut",
    definitions=DEFINITIONS,
    summary="coupled bulk-surface diffusion in a ball and on its sphere, CutFEM + TraceFEM (docs/math.md §10)",
    levels=[0.2, 0.1, 0.05, 0.025],
    level_name="spacing",
    params=[
        Param("k_bulk", float, 1.0, "bulk diffusion k_B", positive=True),
        Param("k_surface", float, 1.0, "surface diffusion k_S", positive=True),
        Param("b_bulk", float, 1.0, "coupling coefficient b_B", minimum=0),
        Param("b_surface", float, 2.0, "coupling coefficient b_S", minimum=0),
        Param("c_bulk", float, 1.0, "bulk reaction c_B (> 0: with 0 the problem has a kernel)", positive=True),
        Param("gamma_g", float, 0.1, "bulk ghost penalty gamma_g (a warning above 1, refused above 1e6)", minimum=0),
        Param("tau_n", float, 1.0, "surface normal-gradient stabilization tau_N (a warning above 100, refused below 1e-8 and "
              "above 1e6)", minimum=0),
        Param("radius", float, 1.0, "radius of the ball", positive=True),
        Param("box", str, None, "background box x0,y0,z0,x1,y1,z1 (default: the ball's box grown by 0.1)"),
        SOLVER_PARAM,
    ],
)
def bulk_surface_cut(spacing, k_bulk, k_surface, b_bulk, b_surface, c_bulk, gamma_g, tau_n, radius, box, solver):
    """One level of the coupled bulk-surface problem; a spacing that does not resolve the sphere (S_h off its area
    by more than 25 %, :func:`~cutfem.problems.common.check_resolution`) is refused.

    The default box is the ball's box grown by 0.1 at every level (:func:`~cutfem.problems.common.box_for`)."""
    for flag, value in (("--k-bulk", k_bulk), ("--k-surface", k_surface), ("--b-bulk", b_bulk), ("--b-surface", b_surface)):
        if not value > 0:
            raise ProblemError(f"{flag} must be positive, got {value}")
    if not c_bulk > 0:
        raise ProblemError(
            "--c-bulk 0 leaves the coupled problem singular (u_B + c / b_B, u_S + c / b_S solves it for every c): "
            "give c_B > 0"
        )
    notes = check_ghost_penalty(gamma_g)  # times b_B k_B: the same ratio to the bulk stiffness
    notes += check_normal_stabilization(tau_n, 1.0, spacing)  # h^-1 beside the tangential stiffness: weight tau_N
    sol = BulkSurfaceSolution(radius, k_bulk, k_surface, b_bulk, b_surface, c_bulk)
    t = Timer()
    with t("geometry"):
        phi = Sphere(radius)
        bg = background_for(phi, spacing, "structured", box)  # default: the ball's box grown by 0.1 at every level
        check_bulk_memory(bg, phi, (NEG,), BULK_BYTES_PER_TET["bulk-surface-cut"], spacing)
        cut = cut_mesh(bg, phi)
        check_resolution(cut, phi, spacing)  # a sphere a few cells across: refused, not solved on a polyhedron
        W = ProductSpace(bulk=CutSpace(cut, NEG), surface=CutSpace(cut, CUT))
        dx, ds = cut.dx(NEG), cut.ds()

    @bilinear_form(symmetric=True)
    def exchange(u, v, w):
        return (b_surface * u[1] - b_bulk * u[0]) * (b_surface * v[1] - b_bulk * v[0])

    with t("assembly"):
        form = (
            b_bulk * k_bulk * stiffness(dx, field="bulk")
            + b_bulk * c_bulk * mass(dx, field="bulk")
            + b_surface * k_surface * tangential_stiffness(ds, field="surface")
            + exchange * ds
        )
        if gamma_g > 0:
            form = form + b_bulk * k_bulk * gamma_g * face_jump_penalty(cut.dF(cut.ghost_facets(NEG)), h_power=1, field="bulk")
        if tau_n > 0:
            form = form + b_surface * k_surface * tau_n * normal_gradient_penalty(cut.dx(CUT), h_power=-1, field="surface")
        K = assemble(form, W)
        rhs = b_bulk * load(sol.f_bulk, dx, degree=2, field="bulk") + b_surface * load(sol.f_surface, ds, field="surface")
        b = assemble(rhs, W)
    with t("solve"):
        # at tau_N = 0, phi_h in the surface field (zero on S_h; the bulk field zero) is a null vector: the solvers name it
        phi_surface = np.zeros(W.n_dofs)
        phi_surface[W.offsets[1]:W.offsets[2]] = cut.values
        x, info = solve(K, b, method=solver, space=W, kernels={"phi_h": phi_surface})
        u_b, u_s = W.split(x)
    with t("errors"):
        rec = {
            "h": W.h,
            "dofs": int(W.n_dofs),
            "dofs_bulk": int(W["bulk"].n_dofs),
            "dofs_surface": int(W["surface"].n_dofs),
            **dict(zip(("l2_error_bulk", "h1_error_bulk"), l2_h1_errors(W["bulk"], u_b, sol.bulk, dx))),
            "l2_error_surface": l2_error(W["surface"], u_s, sol.u_surface),
            "h1_error_surface": h1_error(W["surface"], u_s, sol.grad_surface),
            "area": cut.area,
            "solver": info.method,
            "solver_iterations": info.iterations,
        }
    finish_record(rec, cut, W, notes, t)
    rec["fields"] = LazyFields(
        lambda: {
            "bulk": W["bulk"].elements.to_pyvista(u_h=u_b, u_exact=sol.u_bulk(W["bulk"].dof_points)),
            "surface": with_point_data(cut.to_pyvista(), u_h=W["surface"].surface_vertex_values(u_s), u_exact=sol.u_surface(cut.vertices)),
        }
    )
    return rec

