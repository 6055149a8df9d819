"""Interface problem with a coefficient jump: Nitsche-XFEM (Hansbo-Hansbo; docs/math.md §9).

-div(a_i grad u) = f in Omega_i (NEG inside the sphere |x| = R, POS outside, in the box),
[u] = 0 and [a n . grad u] = 0 on Gamma, u = g strongly on the box boundary (the nodes of the
background's boundary facets, those of one tet: structured or tetwild alike).  One P1 field per side,
u_h = (u_NEG, u_POS) in V_h^NEG x V_h^POS:

    sum_i (a_i grad u_i, grad v_i)_i - ({a n . grad u}, [v]) - ([u], {a n . grad v}) + (lambda / h) ([u], [v])
        + sum_i a_i gamma_g g_i(u_i, v_i) = sum_i (f, v_i)_i

(:func:`cutfem.fem.terms.interface_nitsche`; harmonic or cut-volume weights).

Manufactured solution (smooth on each side, not a polynomial): with psi = |x|^2 - R^2 and
w = sin(x) exp(y / 2) + 2,

    u_i = psi w / a_i.

psi = 0 on Gamma gives [u] = 0, and the flux a_i grad u_i = grad(psi w) is the same smooth field on
both sides, so [a n . grad u] = 0 on every surface, Gamma_h included: the discrete interface then
sees a jump [u] = psi w (1/a_NEG - 1/a_POS) = O(h^2) only, bounded in the contrast.  (A smooth part
common to both sides, v with n . grad v = 0 on Gamma only, would add a flux jump
(a_NEG - a_POS) n . grad v = O(contrast h^2) on Gamma_h, and errors that grow with the contrast.)
f_i = -Lap(psi w) with Lap(psi w) = 6 w + 4 x . grad w + psi Lap w, Lap w = -3/4 (w - 2).

Any other smooth interface {phi = 0} (``--surface``: an ellipsoid, a torus, an expression in x, y, z
or a Python file) takes psi = phi itself: the same construction holds for every psi that vanishes on
Gamma, with grad psi and Lap psi = trace(Hess phi) from the level set (:class:`LevelSetSolution`).
A mesh file has no smooth phi, and is refused.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.norms import l2_h1_errors
from cutfem.fem.forms import assemble
from cutfem.fem.terms import apply_dirichlet, face_jump_penalty, interface_nitsche, load, stiffness
from cutfem.jit import parallel_kernel
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.signed_distance import SignedDistance
from cutfem.geometry.markers import NEG, POS
from cutfem.runs.registry import H_BACKGROUND, LazyFields, Param, ProblemError, register
from cutfem.runs.runner import Timer
from cutfem.solvers.diagnose import SolverError
from cutfem.solvers.solve import solve
from cutfem.fem.spaces import CutSpace, ProductSpace

from .common import finish_record, BACKGROUND_PARAM, BULK_BYTES_PER_TET, ORDER_PARAM, SHAPE_PARAMS, SOLVER_PARAM, background_for, levelset_for, check_bulk_memory, check_ghost_penalty, check_nitsche_penalty, check_resolution, point_rows, value_and_gradient


@parallel_kernel
def _u_and_gradient(x, R2, a, u, grad):
    """u = psi w / a and, when ``grad`` has rows, grad u = (psi grad w + 2 x w) / a at the points x
    (n, 3), in the operation order of the numpy formulas (module docstring)."""
    with_grad = grad.shape[0] > 0
    for i in prange(x.shape[0]):
        x0, x1, x2 = x[i, 0], x[i, 1], x[i, 2]
        psi = x0 * x0 + x1 * x1 + x2 * x2 - R2
        ey = math.exp(0.5 * x1)
        e = math.sin(x0) * ey
        w = e + 2.0
        u[i] = psi * w / a
        if with_grad:
            grad[i, 0] = (math.cos(x0) * ey * psi + 2.0 * x0 * w) / a
            grad[i, 1] = (0.5 * e * psi + 2.0 * x1 * w) / a
            grad[i, 2] = (2.0 * x2 * w) / a


@parallel_kernel
def _source(x, R2, f):
    """f = -Lap(psi w) = -(6 w + 4 x . grad w + psi Lap w), Lap w = -3/4 (w - 2), at the points x (n, 3)."""
    for i in prange(x.shape[0]):
        x0, x1, x2 = x[i, 0], x[i, 1], x[i, 2]
        psi = x0 * x0 + x1 * x1 + x2 * x2 - R2
        ey = math.exp(0.5 * x1)
        e = math.sin(x0) * ey
        f[i] = -(6.0 * (e + 2.0) + 4.0 * (x0 * (math.cos(x0) * ey) + x1 * (0.5 * e)) + psi * (-0.75 * e))


class InterfaceSolution:
    """The manufactured solution above for a sphere of radius R and coefficients a_neg, a_pos.

    u, (u, grad u) and f are compiled loops over the points on all cores: the loads and the errors
    evaluate them at every quadrature point (at 943 thousand unknowns numpy's passes took 3.8 s of
    the run's 9.1 s for (u, grad u); f in numpy took 0.58 s of the load at spacing 0.025).  Equal to
    the numpy formulas to a few ulps (libm and numpy compute sin, cos and exp by different routines)."""

    def __init__(self, radius, a_neg, a_pos):
        self.R, self.a = float(radius), {NEG: float(a_neg), POS: float(a_pos)}

    def _u(self, side, x, with_grad):
        return value_and_gradient(_u_and_gradient, x, self.R**2, self.a[side], gradient=with_grad)

    def u(self, side):
        return lambda x: self._u(side, x, False)[0]

    def solution(self, side):
        """(u, grad u) of a side at the points x (..., 3): grad u = (psi grad w + 2 x w) / a."""
        return lambda x: self._u(side, x, True)

    def f(self, side):
        """f = -div(a grad u) = -Lap(psi w), the same on both sides."""

        def value(x):
            x, pts = point_rows(x)
            out = np.empty(len(pts))
            _source(pts, self.R**2, out)
            return out.reshape(x.shape[:-1])

        return value


def _w(x):
    """w = sin(x) exp(y/2) + 2, grad w and Lap w = -3/4 (w - 2) at the points x (..., 3)."""
    ey = np.exp(0.5 * x[..., 1])
    e = np.sin(x[..., 0]) * ey
    grad = np.stack([np.cos(x[..., 0]) * ey, 0.5 * e, np.zeros_like(e)], axis=-1)
    return e + 2.0, grad, -0.75 * e


class LevelSetSolution:
    """The manufactured solution u_i = phi w / a_i for the interface {phi = 0} of any smooth level
    set (the module docstring): grad u_i = (w grad phi + phi grad w) / a_i and
    f = -(w Lap phi + 2 grad phi . grad w + phi Lap w), Lap phi = trace(Hess phi)."""

    def __init__(self, levelset, a_neg, a_pos):
        self.phi, self.a = levelset, {NEG: float(a_neg), POS: float(a_pos)}

    def solution(self, side):
        def value(x):
            w, gw, _ = _w(x)
            p, gp = self.phi.value(x), self.phi.gradient(x)
            return p * w / self.a[side], (w[..., None] * gp + p[..., None] * gw) / self.a[side]

        return value

    def u(self, side):
        return lambda x: self.phi.value(x) * _w(x)[0] / self.a[side]

    def f(self, side):
        def value(x):
            w, gw, lw = _w(x)
            p, gp, H = self.phi.value(x), self.phi.gradient(x), self.phi.hessian(x)
            return -(w * np.trace(H, axis1=-2, axis2=-1) + 2.0 * np.sum(gp * gw, axis=-1) + p * lw)

        return value


#: the record's entries (saved with the JSON)
DEFINITIONS = {
    "h": H_BACKGROUND,
    "dofs": "unknowns of the coupled system, dofs_inside + dofs_outside: the nodes of the tets of NEG plus those of the "
            "tets of POS (a node of a cut tet counts on both sides)",
    **{f"{norm}_error_{name}": f"{what} over Omega_h,{side} = the {side} cut volume (degree-4 quadrature on its whole tets and cut parts)"
       for norm, what in (("l2", "||u_h - u||_L2"), ("h1", "||grad u_h - grad u||_L2"))
       for name, side in (("inside", "NEG"), ("outside", "POS"))},
}


#: a_inside / a_outside from which a failed solve is explained by the contrast: the inside field's
#: constant is tied to the rest only through the interface terms (measured with the harmonic weights
#: at spacing 0.1: contrasts 1e7 to 1e11 are solved with the rates of 1 : 1, 1e12 is not, by either
#: solver; 1e6 : 1e-6 neither)
CONTRAST_LIMIT = 1e10


def measures(cut):
    """(ds over Gamma_h, {side: dx over the side}, {side: dF over the side's ghost facets}): the
    problem's measures, made here alone (a lifted geometry changes them here)."""
    return cut.ds(), {side: cut.dx(side) for side in (NEG, POS)}, {side: cut.dF(cut.ghost_facets(side)) for side in (NEG, POS)}


@register(
    "interface-poisson-cut",
    definitions=DEFINITIONS,
    summary="-div(a grad u) = f with a jump of a across a sphere or a user's surface, Nitsche-XFEM with ghost penalties (docs/math.md §9)",
    levels=[0.2, 0.1, 0.05, 0.025],
    level_name="spacing",
    params=[
        Param("a_inside", float, 1.0, "coefficient a in the inside domain (NEG)", positive=True),
        Param("a_outside", float, 1.0, "coefficient a in the outside domain (POS)", positive=True),
        Param("weights", str, "harmonic", "averaging weights of the flux", choices=("harmonic", "volume")),
        Param("gamma", float, 10.0, "Nitsche penalty gamma (a warning above 1e3)", positive=True),
        Param("gamma_g", float, 0.1, "ghost penalty gamma_g (times a_i on each side; meaningful in [0.01, 1]: a warning above 1, "
              "refused above 1e6)", minimum=0),
        Param("surface", str, "sphere", "the interface: sphere (of --radius), torus, ellipsoid, an expression in x, y, z "
              "or a Python file defining phi (u_i = phi w / a_i); not a mesh file"),
        Param("radius", float, 0.8, "radius of the interface sphere", positive=True, only=("surface", ("sphere",))),
        *[p for p in SHAPE_PARAMS if p.name != "radius"],
        Param("box", str, "-1.2,-1.2,-1.2,1.2,1.2,1.2", "background box x0,y0,z0,x1,y1,z1"),
        BACKGROUND_PARAM,
        ORDER_PARAM,
        SOLVER_PARAM,
    ],
)
def interface_poisson_cut(spacing, a_inside, a_outside, weights, gamma, gamma_g, surface, radius, R, r, axes, box, solver, order=1,
                          background="structured"):
    """One level of the interface problem; a spacing that does not resolve the sphere (S_h off its area by more
    than 25 %, :func:`~cutfem.problems.common.check_resolution`) is refused.  ``order`` 2: P2 fields on
    both sides, the interface penalty gamma k^2 (as poisson-cut's), the ghost penalties of order 2,
    on Gamma_h and the sides lifted by Theta_h."""
    for name, value in (("--a-inside", a_inside), ("--a-outside", a_outside)):
        if not value > 0:
            raise ProblemError(f"{name} must be positive, got {value}")
    notes = check_ghost_penalty(gamma_g)  # times a_i on each side: the same ratio to each side's stiffness
    notes += check_nitsche_penalty(gamma)
    t = Timer()
    a = {NEG: a_inside, POS: a_outside}
    if surface == "sphere":
        phi, sol = Sphere(radius), InterfaceSolution(radius, a_inside, a_outside)
    else:
        phi = levelset_for(surface, R, r, 1.0, axes)
        if isinstance(phi, SignedDistance):
            raise ProblemError(f"--surface {surface}: a mesh file gives a signed distance, which is not smooth enough for "
                               "the manufactured solution u_i = phi w / a_i; give a named surface, an expression or a "
                               "Python file")
        sol = LevelSetSolution(phi, a_inside, a_outside)
    with t("geometry"):
        bg = background_for(phi, spacing, background, box)
        check_bulk_memory(bg, phi, (NEG, POS), BULK_BYTES_PER_TET["interface-poisson-cut"], spacing)
        cut = cut_mesh(bg, phi, order=order)  # order 2: Gamma_h and the sides lifted by Theta_h (math.md §17)
        check_resolution(cut, phi, spacing)  # a sphere a few cells across: refused, not solved on a polyhedron
        W = ProductSpace(CutSpace(cut, NEG, order=order), CutSpace(cut, POS, order=order))
        ds, dx, ghost = measures(cut)
    with t("assembly"):
        form = interface_nitsche(ds, a_inside, a_outside, gamma * order**2, weights)
        rhs = 0
        for k, side in enumerate((NEG, POS)):
            form = form + a[side] * stiffness(dx[side], field=k)
            if gamma_g > 0:
                form = form + a[side] * gamma_g * face_jump_penalty(ghost[side], h_power=1, field=k)
            rhs = rhs + load(sol.f(side), dx[side], degree=2, field=k)
        K, b = assemble(form, W), assemble(rhs, W)
        outer = W[1]
        boundary = W.offsets[1] + outer.boundary_dofs
        K, b = apply_dirichlet(K, b, boundary, sol.u(POS)(outer.dof_points[outer.boundary_dofs]))
    with t("solve"):
        try:
            x, info = solve(K, b, method=solver, space=W, indefinite_hint=form.indefinite_hint)
        except (SolverError, RuntimeError) as exc:
            contrast = a_inside / a_outside
            if contrast < CONTRAST_LIMIT:
                raise
            raise ProblemError(
                f"--a-inside {a_inside:g} over --a-outside {a_outside:g} is a contrast of {contrast:.1e}: the constant of the "
                f"inside field is tied to the rest only by the interface terms, about {contrast:.0e} times weaker than its "
                "stiffness, which is beyond double precision here (measured at spacing 0.1: 1e11 is solved, 1e12 is "
                f"not; a small inside coefficient, 1e-6 : 1e6, is solved); lower the contrast. The solver said: {exc}"
            ) from exc
        u_neg, u_pos = W.split(x)
    with t("errors"):
        rec = {"h": W.h, "dofs": int(W.n_dofs), "dofs_inside": int(W[0].n_dofs), "dofs_outside": int(W[1].n_dofs)}
        for name, side, u in (("inside", NEG, u_neg), ("outside", POS, u_pos)):
            V = W[0 if side == NEG else 1]
            rec[f"l2_error_{name}"], rec[f"h1_error_{name}"] = l2_h1_errors(V, u, sol.solution(side), dx[side])
        rec["solver"], rec["solver_iterations"] = info.method, info.iterations
    finish_record(rec, cut, W, notes, t)
    n_in, n_out = W[0].elements.n_nodes, W[1].elements.n_nodes  # VTK: the values at the vertices, the first dofs
    rec["fields"] = LazyFields(
        lambda: {
            "inside": W[0].elements.to_pyvista(u_h=u_neg[:n_in], u_exact=sol.u(NEG)(W[0].dof_points[:n_in])),
            "outside": W[1].elements.to_pyvista(u_h=u_pos[:n_out], u_exact=sol.u(POS)(W[1].dof_points[:n_out])),
            "interface": cut.to_pyvista(),
        }
    )
    return rec
