"""Laplace-Beltrami: -Lap_S u + u = f on a closed surface (docs/math.md §4), meshed and cut.

Discrete: (grad_{S_h} u, grad_{S_h} v) + (u, v) + J_h(u, v) = (f^e, v), f^e = f o p.
Cut stabilizations: ``face`` (tau_F h^a J_F), ``normal`` (tau_N h^a (n_h.grad u, n_h.grad v) over the
active tets), ``auto`` (the default: face at order 1, normal at order 2), or ``none`` (then phi_h, zero on
S_h, is a null vector and the solvers refuse the system).
Each stabilization's parameters are accepted with it only.  Errors: L2(S_h) and the H1(S_h) seminorm against u^e = u o p.

Manufactured solutions (exact data derived by hand, checked in the tests against finite differences):

* sphere of radius R: u = x y + z, the sum of spherical harmonics of degree 2 and 1, so
  -Lap_S u = (6/R^2) x y + (2/R^2) z and f = (6/R^2 + 1) x y + (2/R^2 + 1) z on S;
  grad_S u = P grad u with P = I - n n^T.
* torus (R, r), angles t (big circle) and p (tube): u = cos(3t) sin(p).  With s = R + r cos p,
  Lap_S u = (1/(r^2 s)) d_p(s d_p u) + (1/s^2) d_tt u = -cos(3t) sin(p) [(R + 2 r cos p)/(r^2 s) + 9/s^2],
  f = cos(3t) sin(p) [(R + 2 r cos p)/(r^2 s) + 9/s^2 + 1], and
  grad_S u = (d_t u / s) e_t + (d_p u / r) e_p, e_t = (-sin t, cos t, 0), e_p = (-sin p cos t, -sin p sin t, cos p).
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.norms import h1_error, l2_error
from cutfem.fem.forms import assemble
from cutfem.fem.terms import basis_integrals, edge_jump_penalty, face_jump_penalty, load, mass, normal_gradient_penalty, tangential_stiffness
from cutfem.jit import parallel_kernel
from cutfem.geometry.shapes import Sphere, Torus
from cutfem.runs.registry import H_BACKGROUND, H_SURFACE, LazyFields, Param, Problem, ProblemError, register
from cutfem.runs.runner import Timer
from cutfem.solvers.diagnose import SolverError
from cutfem.solvers.solve import solve
from cutfem.fem.spaces import CutSpace, SurfaceP1Space
from cutfem.geometry.markers import CUT
from cutfem.memory import BYTES_PER_ACTIVE_TET

from .common import BACKGROUND_PARAM, ORDER_PARAM, SHAPE_PARAMS, SOLVER_PARAM, SURFACE_BOX_PARAM, TORUS_MESH_PARAMS, check_cut_memory, check_face_stabilization, check_normal_stabilization, check_sphere_levels, check_resolution, background_for, cut_record, face_stabilization_params, levelset_for, point_rows, surface_mesh_for, with_point_data


#: laplace-beltrami-cut's ``--stabilization auto`` at order 2: the normal-gradient term tau_N h^b J_N,
#: (tau_N, b), ngsxfem's weight 1 / h (consistent with the lifted normal, docs/math.md §18)
ORDER2_NORMAL = (1.0, -1.0)

#: the record entries of the Laplace-Beltrami problems (saved in the JSON of a run)
DEFINITIONS = {
    "l2_error": "||u_h - u o p||_{L2(S_h)}, u the manufactured solution at the closest point (degree-4 quadrature on S_h)",
    "h1_error": "||P_h (grad u^e - grad u_h)||_{L2(S_h)}, P_h the tangential projection of S_h, u^e = u o p (degree-4 quadrature)",
}


class SphereSolution:
    """u = x y + z on the sphere |x| = R (centred at 0), extended constantly along the normals:
    each function is evaluated at the closest point R x / |x| of its argument."""

    def __init__(self, R):
        self.R = R

    def _on(self, x):
        x = np.asarray(x, dtype=float)
        return x * (self.R / np.linalg.norm(x, axis=-1, keepdims=True))

    def u(self, x):
        q = self._on(x)
        return q[..., 0] * q[..., 1] + q[..., 2]

    def f(self, x):
        q, R2 = self._on(x), self.R**2
        return (6 / R2 + 1) * q[..., 0] * q[..., 1] + (2 / R2 + 1) * q[..., 2]

    def grad(self, x):
        q = self._on(x)
        g = np.stack([q[..., 1], q[..., 0], np.ones_like(q[..., 0])], axis=-1)
        n = q / self.R
        return g - np.einsum("...d,...d->...", g, n)[..., None] * n


@parallel_kernel
def _torus_solution(x, R, r, mode, values, grad):
    """u (mode 0), f (mode 1) or grad_S u (mode 2) of :class:`TorusSolution` at the points x (n, 3),
    into values (n,) or grad (n, 3); returns the number of points on the axis or the core circle
    (or not finite), where the angles are undefined."""
    bad = 0
    for i in prange(x.shape[0]):
        rho = math.sqrt(x[i, 0] * x[i, 0] + x[i, 1] * x[i, 1])
        w = rho - R
        d = math.sqrt(w * w + x[i, 2] * x[i, 2])
        if not (rho > 0.0 and d > 0.0 and rho < math.inf and d < math.inf):
            bad += 1
            continue
        ct, st = x[i, 0] / rho, x[i, 1] / rho  # cos t, sin t
        cp, sp = w / d, x[i, 2] / d  # cos p, sin p
        c3t = ct * (4.0 * ct * ct - 3.0)  # cos 3t
        s = R + r * cp
        if mode == 0:
            values[i] = c3t * sp
        elif mode == 1:
            values[i] = c3t * sp * ((R + 2.0 * r * cp) / (r * r * s) + 9.0 / (s * s) + 1.0)
        else:
            s3t = st * (3.0 - 4.0 * st * st)  # sin 3t
            a = -3.0 * s3t * sp / s  # d_t u / s, along e_t = (-sin t, cos t, 0)
            b = c3t * cp / r  # d_p u / r, along e_p = (-sin p cos t, -sin p sin t, cos p)
            grad[i, 0] = -a * st - b * sp * ct
            grad[i, 1] = a * ct - b * sp * st
            grad[i, 2] = b * cp
    return bad


class TorusSolution:
    """u = cos(3t) sin(p) on the torus (R, r) about the z axis, extended constantly along the normals.

    The angles t (about the z axis) and p (about the core circle) of a point are those of its
    closest point on the torus, so each function is evaluated from its argument's angles, without
    a projection and without trigonometric calls: cos t, sin t = (x, y) / rho and
    cos p, sin p = (rho - R, z) / d, rho = |(x, y)|, d = |(rho - R, z)|, and cos 3t, sin 3t by the
    triple-angle formulas.  One compiled pass over the points (:func:`_torus_solution`): at the
    torus 768 x 384 (3.5 million quadrature points) the load and the two errors took 1.24 s by the
    closest point and numpy's angles."""

    def __init__(self, R, r):
        self.R, self.r = float(R), float(r)

    def _eval(self, x, mode):
        x, pts = point_rows(x)
        values = np.empty(len(pts) if mode < 2 else 0)
        grad = np.empty((len(pts) if mode == 2 else 0, 3))
        bad = _torus_solution(pts, self.R, self.r, np.int64(mode), values, grad)
        if bad:
            raise ValueError(f"{bad} point(s) lie on the torus axis or its core circle (or are not finite), where the "
                             "manufactured solution's angles are undefined")
        return values.reshape(x.shape[:-1]) if mode < 2 else grad.reshape(x.shape)

    def u(self, x):
        return self._eval(x, 0)

    def f(self, x):
        return self._eval(x, 1)

    def grad(self, x):
        return self._eval(x, 2)


def manufactured(levelset):
    if isinstance(levelset, (Sphere, Torus)) and np.any(levelset.center != 0):
        raise ProblemError(f"the manufactured solution on the {type(levelset).__name__.lower()} needs centre 0")
    if isinstance(levelset, Sphere):
        return SphereSolution(levelset.radius)
    if isinstance(levelset, Torus):
        return TorusSolution(levelset.R, levelset.r)
    raise ProblemError("Laplace-Beltrami has manufactured solutions on the sphere and the torus only")


def _solve_and_measure(space, surface, K, sol, t, solver, multigrid=None, stabilization=None):
    """Load, solve and errors; ``sol``'s functions are extended along the normals (f^e = f o p
    and so on), so they are evaluated at the quadrature points of S_h directly.

    ``stabilization``: the stabilization form contained in K (tau J), or None.  It is assembled
    only when the solver refuses K, to name the cause (:func:`cutfem.solvers.diagnose.diagnose`): a
    stabilization too weak on phi_h (tau_F = 1e-12) or so strong that its null space, which holds
    the constants, swamps the mass term (tau_F = 1e300).  K itself stays one assembly of the whole
    form, so the numbers of a run do not depend on this."""
    with t("assembly"):
        b = assemble(load(sol.f, surface, degree=4), space)
    with t("solve"):
        try:
            u, info = solve(K, b, method=solver, space=space, multigrid=multigrid)
        except SolverError:
            if stabilization is None:
                raise
            u, info = solve(K, b, method=solver, space=space, multigrid=multigrid, stabilization=assemble(stabilization, space))
    with t("errors"):
        rec = {
            "h": space.h,
            "dofs": int(space.n_dofs),
            "l2_error": l2_error(space, u, sol.u),
            "h1_error": h1_error(space, u, sol.grad),
            "solver": info.method,
            "solver_iterations": info.iterations,
        }
    return u, rec


@register
class LaplaceBeltramiMeshed(Problem):
    name = "laplace-beltrami-meshed"
    summary = "-Lap_S u + u = f with a manufactured solution on a triangulated sphere or torus (docs/math.md §4)"
    level_name = "n"
    definitions = {**DEFINITIONS, "h": H_SURFACE}
    level_type = int
    default_levels = [16, 32, 64, 128]
    params = [
        Param("surface", str, "sphere", "sphere or torus", choices=("torus", "sphere")),
        Param("tau_e", float, 0.0, "edge stabilization tau_E", minimum=0),
        *TORUS_MESH_PARAMS,
        SOLVER_PARAM,
        *SHAPE_PARAMS[:3],  # torus and sphere: no ellipsoid, no axes
    ]

    def levels_for(self, levels, params):
        """The sphere's levels must give distinct meshes (:func:`check_sphere_levels`)."""
        levels = super().levels_for(levels, params)
        return check_sphere_levels(levels) if params["surface"] == "sphere" else levels

    def solve_level(self, level, surface, family, tau_e, seed, solver, R, r, radius):
        t = Timer()
        with t("geometry"):
            mesh, exact = surface_mesh_for(surface, level, family, seed, R, r, radius)
            if exact is None:
                raise ProblemError("Laplace-Beltrami needs the sphere or the torus (manufactured solution)")
            sol = manufactured(exact)
            space = SurfaceP1Space(mesh)
        with t("assembly"):
            dS = mesh.ds()
            form = tangential_stiffness(dS) + mass(dS)
            stabilization = tau_e * edge_jump_penalty(dS) if tau_e > 0 else None
            K = assemble(form if stabilization is None else form + stabilization, space)  # one CSR, no sparse sums
        u, rec = _solve_and_measure(space, dS, K, sol, t, solver, stabilization=stabilization)
        rec["area"] = float(assemble(basis_integrals(dS), space).sum())
        rec["time"] = dict(t)
        rec["fields"] = LazyFields(lambda: {"surface": with_point_data(mesh.to_pyvista(), u_h=u, u_exact=sol.u(space.dof_points))})
        return rec


@register
class LaplaceBeltramiCut(Problem):
    name = "laplace-beltrami-cut"
    summary = "-Lap_S u + u = f with a manufactured solution on a cut sphere or torus, face or normal-gradient stabilization (docs/math.md §4)"
    level_name = "spacing"
    definitions = {**DEFINITIONS, "h": H_BACKGROUND}
    level_type = float
    default_levels = [0.2, 0.1, 0.05, 0.025]
    params = [
        Param("surface", str, "sphere", "sphere or torus", choices=("torus", "sphere")),
        BACKGROUND_PARAM,
        SURFACE_BOX_PARAM,
        Param("stabilization", str, "auto", "cut stabilization: face (tau_F h^a J_F), normal (tau_N h^a normal gradient "
              "over the cut tets), auto (face at order 1, normal tau_N h^-1 with tau_N = 1 at order 2), none (the system is "
              "singular, phi_h being a null vector, and every solver refuses it)", choices=("auto", "face", "normal", "none")),
        # each stabilization's parameters with it only: given with another, refused rather than ignored
        *face_stabilization_params(only=("stabilization", ("auto", "face"))),
        Param("tau_n", float, 1.0, "normal-gradient stabilization tau_N (its weight tau_N (s/L)^(a-1): a warning above 100, "
              "refused below 1e-8 and above 1e6)", minimum=0, only=("stabilization", ("normal",))),
        Param("normal_h_power", float, 1.0, "power a of h in the normal-gradient term", only=("stabilization", ("normal",))),
        ORDER_PARAM,
        SOLVER_PARAM,
        *SHAPE_PARAMS[:3],  # torus and sphere: no ellipsoid, no axes
    ]

    @staticmethod
    def measures(cut):
        """(ds over S_h, dF over the interior faces of the cut tets, dx over the cut tets): the
        problem's measures, made here alone (a lifted geometry changes them here)."""
        return cut.ds(), cut.dF(cut.interior_facets(CUT)), cut.dx(CUT)

    @classmethod
    def stabilization_for(cls, stabilization, order, tau_f, face_h_power, tau_n, normal_h_power):
        """(kind, tau_n, normal_h_power): the stabilization that ``stabilization`` names at ``order``.
        ``auto`` is the face term at order 1 and at order 2 the normal-gradient term tau_N h^b with
        (tau_N, b) = :data:`ORDER2_NORMAL`: the face jumps leave the weakest P2 band functions
        uncontrolled (scaled condition number ~ h^-4), the normal gradient keeps it ~ h^-2, and at
        weight h^-1, consistent with the lifted normal, its multigrid iterations stay flat (docs/math.md
        §18).  At order 2 a face parameter beside ``auto`` is refused (it would be ignored)."""
        if stabilization != "auto":
            return stabilization, tau_n, normal_h_power
        if order == 1:
            return "face", tau_n, normal_h_power
        defaults = {p.name: p.default for p in cls.params}
        if tau_f != defaults["tau_f"] or face_h_power != defaults["face_h_power"]:
            raise ProblemError(f"--tau-f {tau_f:g} / --face-h-power {face_h_power:g}: at --order 2 the default stabilization "
                               "is the normal-gradient term; pass --stabilization face to use the face term with these")
        return ("normal",) + ORDER2_NORMAL

    def solve_level(self, level, surface, background, box, stabilization, tau_f, face_h_power, tau_n, normal_h_power, order, solver,
                    R, r, radius):
        """One level; ``order`` 2: P2 trace fields, the terms by quadrature (docs/math.md §18), on
        S_h lifted by Theta_h (§17: the planar S_h, at distance O(h^2) from S, would bound the L2
        rate by 2)."""
        auto = stabilization == "auto"
        stabilization, tau_n, normal_h_power = self.stabilization_for(stabilization, order, tau_f, face_h_power, tau_n, normal_h_power)
        t = Timer()
        with t("geometry"):
            phi = levelset_for(surface, R, r, radius)
            sol = manufactured(phi)
            cut = cut_mesh(background_for(phi, level, background, box), phi, solve_bytes_per_tet=BYTES_PER_ACTIVE_TET, order=order)
            check_resolution(cut, phi, level)
            check_cut_memory(cut, BYTES_PER_ACTIVE_TET, level)
            space = CutSpace(cut, order=order)
        # after the cut's memory checks (a spacing that cannot fit is told so first), before any matrix
        notes = (check_face_stabilization(tau_f, face_h_power, level) if stabilization == "face" else
                 check_normal_stabilization(tau_n, normal_h_power, level, warn=not auto) if stabilization == "normal" else [])
        with t("assembly"):
            dS, faces, band = self.measures(cut)
            form = tangential_stiffness(dS) + mass(dS)
            stab = None
            if stabilization == "face" and tau_f > 0:
                stab = tau_f * face_jump_penalty(faces, h_power=face_h_power)
            elif stabilization == "normal" and tau_n > 0:
                stab = tau_n * normal_gradient_penalty(band, h_power=normal_h_power)
            K = assemble(form if stab is None else form + stab, space)
        multigrid = None
        if stab is not None:
            # the multigrid's coarse spaces also hold phi_h v: the normally linear functions phi_h g
            # are near-null vectors of A_Gamma + M + tau_F J_F that the coarse lattices alone
            # represent worse and worse (cutfem.solvers.multigrid.augmented_hierarchy).  Unit sphere, spacings
            # 0.05, 0.025, 0.0125: CG iterations 11, 11, 11 instead of 27, 38, 51.  The coarsest level
            # at most 400 unknowns: the doubled coarse spaces can be singular there, and the
            # pseudo-inverse of a 1 500-unknown level cost 0.3 s (solve at spacing 0.05: 0.11 s
            # instead of 0.42 s).  The normal-gradient stabilization gains as much: 13, 18, 19
            # iterations instead of 27, 40, 60 (spacings 0.05, 0.025, 0.0125; solve 1.56 s instead
            # of 2.05 s at 0.0125).
            # Order 2: also phi_h^2 v, the normally quadratic functions that only the face penalty sees
            # (augmented_hierarchy): 38, 38 iterations at spacings 0.1, 0.05 instead of 67, 68.
            phi_h = space.interpolate_nodal(space.cut.values)
            multigrid = {"augment": phi_h if order == 1 else np.column_stack([phi_h, phi_h**2]), "coarse_size": 400}
        u, rec = _solve_and_measure(space, dS, K, sol, t, solver, multigrid, stabilization=stab)
        rec.update(cut_record(cut))
        if notes:
            rec["warnings"] = notes
        rec["area"] = float(assemble(basis_integrals(dS), space).sum())
        rec["time"] = dict(t)
        rec["fields"] = LazyFields(
            # of P2 the values at the vertices of S_h (VTK draws them linear on each triangle)
            lambda: {"surface": with_point_data(cut.to_pyvista(), u_h=space.surface_vertex_values(u), u_exact=sol.u(cut.vertices))}
        )
        return rec
