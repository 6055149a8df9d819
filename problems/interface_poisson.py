"""Interface problem with a coefficient jump: Nitsche-XFEM (Hansbo-Hansbo; docs/math.md §9).

-div(a_i grad u) = f in Omega_i (NEG inside the sphere |x| = R, POS outside, in the box),
[u] = 0 and [a n . grad u] = 0 on Gamma, u = g strongly on the box boundary.  One P1 field per side,
u_h = (u_NEG, u_POS) in V_h^NEG x V_h^POS:

    sum_i (a_i grad u_i, grad v_i)_i - ({a n . grad u}, [v]) - ([u], {a n . grad v}) + (lambda / h) ([u], [v])
        + sum_i a_i gamma_g g_i(u_i, v_i) = sum_i (f, v_i)_i

(:func:`cutfem.forms.interface_nitsche`; harmonic or cut-volume weights).

Manufactured solution (smooth on each side, not a polynomial): with psi = |x|^2 - R^2 and
w = sin(x) exp(y / 2) + 2,

    u_i = psi w / a_i.

psi = 0 on Gamma gives [u] = 0, and the flux a_i grad u_i = grad(psi w) is the same smooth field on
both sides, so [a n . grad u] = 0 on every surface, Gamma_h included: the discrete interface then
sees a jump [u] = psi w (1/a_NEG - 1/a_POS) = O(h^2) only, bounded in the contrast.  (A smooth part
common to both sides, v with n . grad v = 0 on Gamma only, would add a flux jump
(a_NEG - a_POS) n . grad v = O(contrast h^2) on Gamma_h, and errors that grow with the contrast.)
f_i = -Lap(psi w) with Lap(psi w) = 6 w + 4 x . grad w + psi Lap w, Lap w = -3/4 (w - 2).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from cutfem.cut import cut_mesh
from cutfem.errors import l2_h1_errors
from cutfem.forms import apply_dirichlet, assemble, face_jump_penalty, interface_nitsche, load, stiffness
from cutfem.levelset import Sphere
from cutfem.markers import NEG, POS
from cutfem.registry import LazyFields, Param, ProblemError, register
from cutfem.solve import solve
from cutfem.spaces import CutP1Space, ProductSpace

from .common import Timer, background_for, cut_record


@njit(cache=True, error_model="numpy")
def _u_and_gradient(x, R2, a, u, grad):
    """u = psi w / a and grad u = (psi grad w + 2 x w) / a at the points x (n, 3), in the operation
    order of :meth:`InterfaceSolution.solution`'s numpy form."""
    for i in range(x.shape[0]):
        x0, x1, x2 = x[i, 0], x[i, 1], x[i, 2]
        psi = x0 * x0 + x1 * x1 + x2 * x2 - R2
        ey = math.exp(0.5 * x1)
        e = math.sin(x0) * ey
        w = e + 2.0
        u[i] = psi * w / a
        grad[i, 0] = (math.cos(x0) * ey * psi + 2.0 * x0 * w) / a
        grad[i, 1] = (0.5 * e * psi + 2.0 * x1 * w) / a
        grad[i, 2] = (2.0 * x2 * w) / a


class InterfaceSolution:
    """The manufactured solution above for a sphere of radius R and coefficients a_neg, a_pos."""

    def __init__(self, radius, a_neg, a_pos):
        self.R, self.a = float(radius), {NEG: float(a_neg), POS: float(a_pos)}

    def _parts(self, x, gradient=True):
        """psi, w, grad w (None unless ``gradient``) and Lap w at the points x (..., 3): each
        factor (sin x, cos x, exp(y / 2)) evaluated once, the gradient written in place."""
        x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
        psi = x0 * x0 + x1 * x1 + x2 * x2 - self.R**2
        ey = np.exp(0.5 * x1)
        e = np.sin(x0) * ey
        grad_w = None
        if gradient:
            grad_w = np.empty(np.shape(x))
            np.multiply(np.cos(x0), ey, out=grad_w[..., 0])
            np.multiply(0.5, e, out=grad_w[..., 1])
            grad_w[..., 2] = 0.0
        return psi, e + 2.0, grad_w, -0.75 * e

    def u(self, side):
        def value(x):
            psi, w, _, _ = self._parts(x, gradient=False)
            return psi * w / self.a[side]

        return value

    def solution(self, side):
        """(u, grad u) of a side at the points x (..., 3): grad u = (psi grad w + 2 x w) / a, by one
        compiled loop over the points (the errors evaluate it at every quadrature point: at 943
        thousand unknowns numpy's passes over the parts took 3.8 s of the run's 9.1 s).  Equal to
        the numpy expression to a few ulps (libm and numpy compute sin, cos and exp by different
        routines)."""
        R2, a = self.R**2, self.a[side]

        def value(x):
            x = np.asarray(x, dtype=float)
            if x.ndim == 0 or x.shape[-1] != 3:
                raise ValueError(f"points must have shape (..., 3), got {x.shape}")
            pts = np.ascontiguousarray(x.reshape(-1, 3))
            u, grad = np.empty(len(pts)), np.empty((len(pts), 3))
            _u_and_gradient(pts, R2, a, u, grad)
            return u.reshape(x.shape[:-1]), grad.reshape(x.shape)

        return value

    def f(self, side):
        def value(x):
            psi, w, grad_w, lap_w = self._parts(x)
            return -(6.0 * w + 4.0 * np.einsum("...d,...d->...", x, grad_w) + psi * lap_w)

        return value


@register(
    "interface-poisson-cut",
    summary="-div(a grad u) = f with a jump of a across a sphere, Nitsche-XFEM with ghost penalties (docs/math.md §9)",
    levels=[0.2, 0.1, 0.05, 0.025],
    level_name="spacing",
    params=[
        Param("a_inside", float, 1.0, "coefficient a in the inside domain (NEG)", minimum=0),
        Param("a_outside", float, 1.0, "coefficient a in the outside domain (POS)", minimum=0),
        Param("weights", str, "harmonic", "averaging weights of the flux", choices=("harmonic", "volume")),
        Param("gamma", float, 10.0, "Nitsche penalty gamma", minimum=0),
        Param("gamma_g", float, 0.1, "ghost penalty gamma_g (times a_i on each side)", minimum=0),
        Param("radius", float, 0.8, "radius of the interface sphere", minimum=0),
        Param("box", str, "-1.2,-1.2,-1.2,1.2,1.2,1.2", "background box x0,y0,z0,x1,y1,z1"),
        Param("solver", str, "auto", "linear solver", choices=("auto", "direct", "cg-mg", "cg-amg", "cg-jacobi")),
    ],
)
def interface_poisson_cut(spacing, a_inside, a_outside, weights, gamma, gamma_g, radius, box, solver):
    """One level of the interface problem."""
    for name, value in (("--a-inside", a_inside), ("--a-outside", a_outside)):
        if not value > 0:
            raise ProblemError(f"{name} must be positive, got {value}")
    t = Timer()
    sol = InterfaceSolution(radius, a_inside, a_outside)
    a = {NEG: a_inside, POS: a_outside}
    with t("geometry"):
        phi = Sphere(radius)
        cut = cut_mesh(background_for(phi, spacing, "structured", box), phi)
        W = ProductSpace(CutP1Space(cut, NEG), CutP1Space(cut, POS))
    with t("assembly"):
        form = interface_nitsche(cut.ds(), a_inside, a_outside, gamma, weights)
        rhs = 0
        for k, side in enumerate((NEG, POS)):
            form = form + a[side] * stiffness(cut.dx(side), field=k)
            if gamma_g > 0:
                form = form + a[side] * gamma_g * face_jump_penalty(cut.dF(cut.ghost_facets(side)), h_power=1, field=k)
            rhs = rhs + load(sol.f(side), cut.dx(side), degree=2, field=k)
        K, b = assemble(form, W), assemble(rhs, W)
        outer = W[1]
        boundary = W.offsets[1] + outer.boundary_dofs
        K, b = apply_dirichlet(K, b, boundary, sol.u(POS)(outer.dof_points[outer.boundary_dofs]))
    with t("solve"):
        x, info = solve(K, b, method=solver, space=W, indefinite_hint=f"raise the Nitsche penalty (--gamma {gamma:g} is below its stability bound)")
        u_neg, u_pos = W.split(x)
    with t("errors"):
        rec = {"h": W.h, "dofs": int(W.n_dofs), "dofs_inside": int(W[0].n_dofs), "dofs_outside": int(W[1].n_dofs)}
        for name, side, u in (("inside", NEG, u_neg), ("outside", POS, u_pos)):
            V, dx = W[0 if side == NEG else 1], cut.dx(side)
            rec[f"l2_error_{name}"], rec[f"h1_error_{name}"] = l2_h1_errors(V, u, sol.solution(side), dx)
        rec["solver"], rec["solver_iterations"] = info.method, info.iterations
    rec.update(cut_record(cut))
    rec["time"] = dict(t)
    rec["fields"] = LazyFields(
        lambda: {
            "inside": W[0].elements.to_pyvista(u_h=u_neg, u_exact=sol.u(NEG)(W[0].dof_points)),
            "outside": W[1].elements.to_pyvista(u_h=u_pos, u_exact=sol.u(POS)(W[1].dof_points)),
            "interface": cut.to_pyvista(),
        }
    )
    return rec
