"""The stabilized mean curvature vector (docs/math.md §3), on triangulated and on cut surfaces.

Find H_h in [V_h]^3 with, for all v in [V_h]^3,

    (H_h, v)_{S_h} + J_h(H_h, v) = (grad_{S_h} x, grad_{S_h} v)_{S_h}.

Component k: (M + J) H_k = A x_k with M the surface mass matrix, A the tangential stiffness and x_k
the nodal values of the coordinate k; one matrix, one factorization, three right-hand sides.
A x_k is formed without A: b_i = sum_K |S_K| grad_{S_h} phi_i (:func:`cutfem.fem.terms.position_load`).
Stabilization: meshed J = tau_E J_E (edge conormal-gradient jumps, weighted by the global
h = N^(-1/2)); cut J = tau_E J_E + tau_F J_F (face normal-gradient jumps of the active mesh, times
h^a, a = ``face_h_power``, 0 in the paper), or J = tau_N J_N, the normal-gradient term over the cut
tets (h^a, a = ``normal_h_power``; default tau_N h_T^-1, tau_N = sqrt(3), i.e. 1 / spacing on a
Kuhn box, h_T = sqrt(3) spacing the longest edge).  Exact field for errors: H^e = H o p, at the closest point of
each quadrature point of S_h (of Theta_h(S_h) at order 2).

Order 2 (``--order 2``, docs/math.md §18): P2 trace fields on the lifted cut Theta_h(S_h); every term
goes by quadrature with the per-point normals of the lifted surface, the position load too (it is
A x with x the P2 field of the lifted node positions, exactly).  Default there: the face term with
a = 1, the jumps of the first and second normal derivatives weighted h and h^3 / 4, plus the
normal-gradient term tau_N h J_N, tau_N = 1: the face jumps alone leave the weakest P2 band functions
uncontrolled (scaled condition number ~ h^-4), the normal gradient at weight h controls them at
little cost in accuracy (docs/math.md §18 compares the stabilizations).

Units of length (choice).  Under x -> s x the mass term scales as s^2, the jumps do not: J_E as
s^-1 (h = N^(-1/2) is a number) and h^a J_F as s^a, so the paper's tau_E = tau_F = 1/10 are
numbers for a surface of size about 1.  With ``length_scale`` L the stabilization is that of the
surface measured in units of L, tau_E h L^3 J_E and tau_F L^(2-a) J_F (tau_E L^3 J_E on a cut too):
the solution for the surface scaled by s with L scaled by s is H_h / s exactly.  Default L = 1 (the
paper).  A surface whose size sqrt(area / 4 pi) is outside [L/10, 10 L] is refused
(:func:`check_length_scale`): there the stabilization swamps the mass term or vanishes beside it
(the unit sphere mesh of 642 nodes given in metres as 1 mm: H_h . n R = 2.9e-6 instead of 2; the
cut sphere of radius 100 at spacing 10: relative L2 error 0.69 against 0.0054 at radius 1).
"""

from __future__ import annotations

import numpy as np

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.norms import discrete_error, l2_error
from cutfem.fem.forms import assemble
from cutfem.fem.terms import basis_integrals, edge_jump_penalty, face_jump_penalty, mass, normal_gradient_penalty, position_load
from cutfem.runs.registry import H_BACKGROUND, H_SURFACE, LazyFields, Param, Problem, ProblemError, register
from cutfem.runs.runner import Timer
from cutfem.solvers.solve import solve
from cutfem.fem.spaces import CutSpace, SurfaceP1Space
from cutfem.geometry.markers import CUT

from .common import BACKGROUND_PARAM, ORDER_PARAM, SHAPE_PARAMS, SOLVER_PARAM, SURFACE_BOX_PARAM, TORUS_MESH_PARAMS, USER_SURFACES, check_cut_memory, check_resolution, check_sphere_levels, background_for, cut_record, face_stabilization_params, has_exact, levelset_for, mesh_file_notes, surface_mesh_for
from .common import check_edge_stabilization, check_face_stabilization, check_normal_stabilization, pin_unseen_nodes

#: relative residual of the iterative solves (the library's default is 1e-8).  The invariant
#: int_{S_h} H_h = 0 (docs/math.md §3) needs no tighter tolerance: the solvers end with the Galerkin
#: correction on the constants, which makes it hold to round-off (3e-13 on the cut torus at spacing
#: 0.0125).  Against 1e-8, measured at spacing 0.05 (cut) and n = 128 (meshed): the L2 errors
#: differ by 5e-8 and 1.5e-7 relative, the energy-norm algebraic error is 1e-8 relative (spacing
#: 0.0125), and CG needs 20 iterations instead of 27 at spacing 0.0125 (with the multigrid's
#: K-cycles; 23 instead of 31 with W-cycles).
SOLVER_TOL = 1e-6
#: what the stages after the cut add to the resident memory per active tet, for the memory checks
#: before the cut (:func:`cutfem.geometry.cut.cut_mesh`'s ``solve_bytes_per_tet``, on the predicted active
#: tets) and before the space is built (:func:`~cutfem.problems.common.check_cut_memory`); measured
#: 152, 155, 162 and about 157 bytes at spacings 0.0125 to 0.0015625, see :mod:`cutfem.memory`
BYTES_PER_ACTIVE_TET = 200

#: the record entries of the mean curvature problems (saved in the JSON of a run)
DEFINITIONS = {
    "l2_error": "||H_h - H^e||_{L2(S_h)}, H^e = H o p the exact mean curvature vector at the closest point, the three components together (degree-4 quadrature on S_h)",
    "discrete_error": "sqrt(e^T M e), e = H^e(x_i) - H_h(x_i) at the nodes, M the mass matrix on the surface: ||pi_h H^e - H_h||_{L2(S_h)}",
    "area_error": "|area(S_h) - area(S)|, area(S_h) = 1^T M 1",
}


#: a surface of size sqrt(area / 4 pi) outside [L / LENGTH_SCALE_RANGE, L * LENGTH_SCALE_RANGE] is refused
LENGTH_SCALE_RANGE = 10.0

#: the power a of h in the face term J_F of ``--stabilization auto`` at order 2: with a = 1 the jumps of
#: the first and second normal derivatives weigh h and h^3 / 4, the ghost penalty of order 2; the most
#: accurate of the stabilizations measured (docs/math.md §18).  Order 1 keeps the paper's a = 0.
ORDER2_FACE_H_POWER = 1.0
#: the normal-gradient term tau_N h^b J_N that ``--stabilization auto`` adds to the face term at order 2
#: (tau_N, b): the face jumps do not see the normally quadratic P2 band functions, so alone they leave the
#: scaled condition number growing like h^-4; tau_N h J_N controls those functions (the condition number
#: then grows like h^-1), and at weight h it costs little accuracy (docs/math.md §18)
ORDER2_NORMAL = (1.0, 1.0)


def mean_curvature_form(surface, tau_e=0.0, tau_f=0.0, faces=None, face_h_power=0.0, length_scale=1.0, tau_n=0.0, band=None,
                        normal_h_power=-1.0):
    """The bilinear form of K = M + tau_E L^3 J_E + tau_F L^(2-a) J_F + tau_N L^(1-b) J_N on the
    measure ``surface`` (S_h), J_F over the facet measure ``faces`` (cut case, times h^a, a =
    ``face_h_power``), J_N the normal-gradient term over the tets ``band`` (times h^b, b =
    ``normal_h_power``; beside the mass it scales as s^(b-1)), L = ``length_scale`` (the module's
    note on units; 1 in the paper).  Assembled as one form: on a
    structured box the mass and the face penalty sum into one set of lattice slots, on a
    triangulated surface the mass and the edge penalty into one set of node and pair values.

    A stabilized form is refused (ProblemError, :func:`check_length_scale`) when the surface's size
    is far from L: every path to the system goes through here (``cutfem run``, :func:`cutfem.run`,
    the problems' levels and scripts calling this function or :func:`mean_curvature_system`)."""
    if tau_e > 0 or tau_f > 0 or tau_n > 0:
        check_length_scale(surface.size, length_scale, 2.0 - face_h_power if tau_f > 0 else 1.0 - normal_h_power if tau_n > 0 else 3)
    form = mass(surface)
    if tau_e > 0:
        form = form + (tau_e * length_scale**3) * edge_jump_penalty(surface)
    if tau_f > 0:
        form = form + (tau_f * length_scale ** (2.0 - face_h_power)) * face_jump_penalty(faces, h_power=face_h_power)
    if tau_n > 0:
        form = form + (tau_n * length_scale ** (1.0 - normal_h_power)) * normal_gradient_penalty(band, h_power=normal_h_power)
    return form


def mean_curvature_system(space, surface, tau_e=0.0, tau_f=0.0, faces=None, face_h_power=0.0, length_scale=1.0, tau_n=0.0, band=None,
                          normal_h_power=-1.0):
    """(K, B): the matrix of :func:`mean_curvature_form` on ``space`` and the right-hand sides
    B = A X, (n, 3), computed without A (:func:`cutfem.fem.terms.position_load`)."""
    form = mean_curvature_form(surface, tau_e, tau_f, faces, face_h_power, length_scale, tau_n, band, normal_h_power)
    return assemble(form, space), assemble(position_load(surface), space)


def check_length_scale(area, length_scale, power, flag="--length-scale"):
    """Refuse (ProblemError) a surface of area ``area`` whose size sqrt(area / 4 pi) is not within a
    factor LENGTH_SCALE_RANGE of the length scale L of the stabilization, whose weight relative to
    the mass term goes as (L / size)^``power``; the message gives the L to pass (the size, rounded
    to one significant digit)."""
    if not length_scale > 0:
        raise ProblemError(f"{flag}: the length scale must be a positive length, got {length_scale:g}")
    size = float(np.sqrt(area / (4.0 * np.pi)))
    ratio = size / length_scale
    if not 1.0 / LENGTH_SCALE_RANGE <= ratio <= LENGTH_SCALE_RANGE:
        suggest = float(f"{size:.0e}")
        raise ProblemError(
            f"the surface's size sqrt(area / 4 pi) = {size:.3g} is {ratio:.3g} times the length scale L = {length_scale:g} "
            f"of the stabilization: its weight relative to the mass term goes as (L / size)^{power:g}, so the result would be "
            f"that of a surface of size 1 with a stabilization {ratio ** -power:.3g} times the paper's (docs/math.md §3); pass "
            f"{flag} {suggest:g} (the unit in which the surface has size about 1; H_h scales exactly with it)"
        )


def lumped_guess(B, ones_M):
    """The starting guess H_0 = M_L^{-1} A x of the iterative solves on a triangulated surface, M_L
    the lumped mass matrix (diagonal ``ones_M`` = M 1) and A x = ``B``: the classical discrete mean
    curvature vector, the solution when the mass is lumped and the edge term left out.  On the
    structured torus grid it is close, residual 1.4e-4 |B| at n = 768 (CG with the multigrid: 8
    iterations against 17 from zero; 12 against 18 at n = 256); on the flipped and perturbed
    families it is noisy (residuals 2.6e3-7e3 |B|), and the solver starts those columns from zero
    (:func:`cutfem.solvers.solve.solve`).  None when a node has no mass (a cut surface's nearly empty
    pieces: the guess would be unbounded)."""
    ones_M = np.asarray(ones_M, dtype=float)
    return B / ones_M[:, None] if np.all(ones_M > 0) else None


def _common_record(space, ones_M, H, levelset, solve_info):
    """The record entries of both kinds; ``ones_M`` = 1^T M, the integrals of the basis functions
    over S_h (:func:`cutfem.fem.terms.basis_integrals`)."""
    rec = {
        "h": space.h,
        "dofs": int(space.n_dofs),
        "area": float(ones_M.sum()),
        # exact for P1: int_{S_h} H_h = 1^T M H (einsum: a BLAS product would leave its threads spinning)
        "integral_H": np.einsum("i,ij->j", ones_M, H).tolist(),
        "solver": solve_info.method,
        "solver_iterations": solve_info.iterations,
        "solver_residual": solve_info.residual,
    }
    if levelset is not None and levelset.area is not None:
        rec["area_error"] = abs(rec["area"] - levelset.area)
    return rec


@register
class MeanCurvatureMeshed(Problem):
    name = "mean-curvature-meshed"
    summary = "stabilized mean curvature vector on a triangulated closed surface (docs/math.md §3, meshed)"
    level_name = "n"
    level_type = int
    default_levels = [16, 32, 64, 128]
    components = 3
    definitions = {**DEFINITIONS, "h": H_SURFACE}
    params = [
        Param("surface", str, "torus", "torus, sphere, or a closed mesh file (STL, OBJ, PLY, VTK, ...)", choices=("torus", "sphere"), files=True),
        Param("tau_e", float, 0.1, "edge stabilization tau_E (a warning above 1)", minimum=0),
        *TORUS_MESH_PARAMS,
        SOLVER_PARAM,
        Param("length_scale", float, 1.0, "length L in which tau_E is given: tau_E h L^3 J_E (the surface's size, in its file's unit)", positive=True),
        *SHAPE_PARAMS,
    ]

    def levels_for(self, levels, params):
        """A mesh file has one resolution that the levels n do not change: one level (default 1).
        The sphere's levels must give distinct meshes (:func:`check_sphere_levels`)."""
        if params["surface"] == "sphere":
            return check_sphere_levels(super().levels_for(levels, params))
        if not (isinstance(params["surface"], str) and params["surface"] not in ("torus", "sphere")):
            return super().levels_for(levels, params)
        if levels is None:
            return [1]
        if len(list(levels)) > 1:
            raise ProblemError(f"--surface {params['surface']}: a mesh file is solved as it is, at one resolution that the "
                               f"levels n do not change; give one level (--levels 1) instead of {len(list(levels))}")
        return levels

    def solve_level(self, level, surface, family, tau_e, seed, solver, length_scale, R, r, radius, axes):
        t = Timer()
        with t("geometry"):
            mesh, exact = surface_mesh_for(surface, level, family, seed, R, r, radius)
            notes = check_edge_stabilization(tau_e)
            space = SurfaceP1Space(mesh)
        with t("assembly"):
            K, B = mean_curvature_system(space, mesh.ds(), tau_e=tau_e, length_scale=length_scale)
            ones_M = assemble(basis_integrals(mesh.ds()), space)
        with t("solve"):
            H, info = solve(K, B, method=solver, space=space, tol=SOLVER_TOL, x0=lumped_guess(B, ones_M))
        with t("errors"):
            rec = _common_record(space, ones_M, H, exact, info)
            rec.update(triangles=int(mesh.n_triangles), edges=int(mesh.n_edges))
            if notes:
                rec["warnings"] = notes
            if exact is not None:
                He = exact.exact_mean_curvature_vector
                rec["l2_error"] = l2_error(space, H, He)
                rec["discrete_error"] = discrete_error(space, He(space.dof_points) - H)
            elif surface not in ("torus", "sphere"):
                rec["notes"] = ["no l2_error and discrete_error columns: a surface mesh file has no exact mean curvature; "
                                "run mean-curvature-cut with the surface as an expression or a Python file to get errors"]
        rec["time"] = dict(t)
        rec["fields"] = LazyFields(
            lambda: {"surface": _surface_fields(mesh.to_pyvista(), H, None if exact is None else exact.exact_mean_curvature_vector(space.dof_points))}
        )
        return rec


@register
class MeanCurvatureCut(Problem):
    name = "mean-curvature-cut"
    summary = "stabilized mean curvature vector on the zero level set of a P1 level set on tetrahedra, or P2 on its lifted cut with --order 2 (docs/math.md §3, §18, cut)"
    level_name = "spacing"
    level_type = float
    default_levels = [0.2, 0.1, 0.05, 0.025]
    components = 3
    definitions = {**DEFINITIONS, "h": H_BACKGROUND}
    params = [
        Param("surface", str, "torus", f"torus, sphere, ellipsoid, {USER_SURFACES}; H^e is exact at the closest point"),
        BACKGROUND_PARAM,
        SURFACE_BOX_PARAM,
        Param("stabilization", str, "auto", "cut stabilization: face (tau_F h^a J_F), normal (tau_N h^a normal gradient over "
              "the cut tets), auto (face; at order 2 face with a = 1 plus normal tau_N h, tau_N = 1)", choices=("auto", "face", "normal")),
        *face_stabilization_params(only=("stabilization", ("auto", "face"))),
        Param("tau_n", float, float(np.sqrt(3.0)), "normal-gradient stabilization tau_N (sqrt 3: 1 / spacing with a = -1 on a "
              "Kuhn box)", minimum=0, only=("stabilization", ("normal",))),
        Param("normal_h_power", float, -1.0, "power a of h_T in the normal-gradient term", only=("stabilization", ("normal",))),
        Param("tau_e", float, 0.0, "edge stabilization tau_E", minimum=0),
        ORDER_PARAM,
        SOLVER_PARAM,
        Param("length_scale", float, 1.0, "length L in which tau_F, tau_E are given: tau_F L^(2-a) J_F, tau_E L^3 J_E (the surface's size)", positive=True),
        *SHAPE_PARAMS,
    ]

    @staticmethod
    def measures(cut):
        """(ds over S_h, dF over the interior faces of the cut tets, dx over the cut tets): the
        problem's measures, made here alone (a lifted cut lifts them)."""
        return cut.ds(), cut.dF(cut.interior_facets(CUT)), cut.dx(CUT)

    @staticmethod
    def stabilization_for(stabilization, order, tau_f, face_h_power, tau_n, normal_h_power):
        """(kind, tau_f, face_h_power, tau_n, normal_h_power), an unused term's coefficient 0.
        ``auto`` is the face term, with the paper's a = ``face_h_power`` (0) at order 1, and at order 2
        the face term with a = :data:`ORDER2_FACE_H_POWER` plus the normal-gradient term
        :data:`ORDER2_NORMAL` (an --face-h-power given there is refused: it would be ignored)."""
        if stabilization == "normal":
            return "normal", 0.0, face_h_power, tau_n, normal_h_power
        if stabilization == "auto" and order == 2:
            if face_h_power != 0.0:
                raise ProblemError(f"--face-h-power {face_h_power:g}: at --order 2 the default stabilization takes a = "
                                   f"{ORDER2_FACE_H_POWER:g}; pass --stabilization face with --face-h-power to choose another power")
            return ("face", tau_f, ORDER2_FACE_H_POWER) + ORDER2_NORMAL
        return "face", tau_f, face_h_power, 0.0, normal_h_power

    def solve_level(self, level, surface, background, box, stabilization, tau_f, face_h_power, tau_n, normal_h_power, tau_e, order,
                    solver, length_scale, R, r, radius, axes):
        """One level; ``order`` 2: P2 trace fields on S_h lifted by Theta_h (docs/math.md §17-18).  An
        edge penalty (``tau_e`` > 0) is refused at order 2 before the geometry is built: J_E has its
        P1 form only (:func:`cutfem.fem.terms.edge_jump_penalty`)."""
        if order == 2 and tau_e > 0:
            raise ProblemError(f"--tau-e {tau_e:g} at --order 2: the edge penalty J_E has its P1 form only (the edges of the "
                               "lifted S_h are curved and no quadrature measure covers them); leave --tau-e out (0) and "
                               "stabilize with the default face term or --stabilization normal")
        kind, tau_f, face_h_power, tau_n, normal_h_power = self.stabilization_for(stabilization, order, tau_f, face_h_power, tau_n,
                                                                                  normal_h_power)
        t = Timer()
        with t("geometry"):
            phi = levelset_for(surface, R, r, radius, axes)
            bg = background_for(phi, level, background, box)
            cut = cut_mesh(bg, phi, solve_bytes_per_tet=BYTES_PER_ACTIVE_TET, order=order)
            check_resolution(cut, phi, level)
            check_cut_memory(cut, BYTES_PER_ACTIVE_TET, level)
            space = CutSpace(cut, order=order)
        # after the cut's memory checks (a spacing that cannot fit is told so first), before any matrix
        notes = (check_face_stabilization(tau_f, face_h_power, level, length_scale) if kind == "face" else
                 check_normal_stabilization(tau_n, normal_h_power, level, length_scale, warn=False))
        with t("assembly"):
            dS, faces, band = self.measures(cut)
            ones_M = assemble(basis_integrals(dS), space)
            K, B = mean_curvature_system(space, dS, tau_e=tau_e, tau_f=tau_f, faces=faces, face_h_power=face_h_power,
                                         length_scale=length_scale, tau_n=tau_n, band=band, normal_h_power=normal_h_power)
            K, B, unseen = pin_unseen_nodes(K, B, space)  # S_h along grid faces: nodes no term sees, fixed at 0
        # order 2: the multigrid's coarse spaces also hold phi_h v and phi_h^2 v, as laplace-beltrami-cut's (its note)
        phi_h = space.interpolate_nodal(cut.values) if order == 2 else None
        multigrid = None if order == 1 else {"augment": np.column_stack([phi_h, phi_h**2]), "coarse_size": 400}
        with t("solve"):
            H, info = solve(K, B, method=solver, space=space, tol=SOLVER_TOL, multigrid=multigrid)
        exact = phi if has_exact(phi) else None
        with t("errors"):
            rec = _common_record(space, ones_M, H, exact, info)
            rec.update(cut_record(cut))
            if unseen:
                rec["unseen_nodes"] = unseen
            if notes:
                rec["warnings"] = notes
            if exact is not None:
                rec["l2_error"] = l2_error(space, H, exact.exact_mean_curvature_vector)
        file_notes = mesh_file_notes(phi, level)  # a mesh file: no errors, and facets the spacing may resolve
        if file_notes:
            rec["notes"] = file_notes
        rec["time"] = dict(t)
        rec["fields"] = LazyFields(
            lambda: {
                "surface": _surface_fields(
                    cut.to_pyvista(), space.surface_vertex_values(H), None if exact is None else exact.exact_mean_curvature_vector(cut.vertices)
                ),
                "active_mesh": _point_fields(cut.active_mesh_pyvista(), {"H_h": H[: len(space.node_ids)]}),  # P2: its P1 prefix
            }
        )
        return rec


def _point_fields(ds, arrays):
    for k, v in arrays.items():
        ds.point_data[k] = np.asarray(v)
    return ds


def _surface_fields(poly, H, He):
    """Point data on S_h: H_h, |H_h|, the signed mean curvature H_h . n, and with an exact field
    H^e (``H_exact``) the pointwise error |H^e - H_h| (``error``).  n at a vertex is VTK's point
    normal: the normalized sum of the unit normals of the triangles at the vertex, not weighted by
    their areas (on a cut surface that gives its slivers a full say; area weights were no closer to
    the sphere's normals: 7.5 against 6.6 degrees at worst at spacing 0.2).  The triangles are
    oriented outward, so n is the outward normal and a sphere of radius R gives 2 / R."""
    normals = poly.compute_normals(point_normals=True, cell_normals=False, auto_orient_normals=False, consistent_normals=False, split_vertices=False)
    arrays = {"H_h": H, "|H_h|": np.linalg.norm(H, axis=1), "mean_curvature": np.einsum("ij,ij->i", H, normals.point_data["Normals"])}
    if He is not None:
        arrays["H_exact"] = He
        arrays["error"] = np.linalg.norm(He - H, axis=1)
    return _point_fields(poly, arrays)
