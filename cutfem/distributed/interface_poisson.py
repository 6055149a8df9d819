"""interface-poisson-cut on several ranks (docs/math.md §9): Nitsche-XFEM with one P1 field per
side, the ghost penalty of each side on every face once, the outer box's Dirichlet condition, solved
by PETSc.

The forms are the serial problem's (:func:`cutfem.problems.interface_poisson.interface_poisson_cut`):
on the owned cells (a slab of a structured box, or cells of an unstructured mesh) the product space
of the two sides, the stiffness a_i (grad u_i, grad v_i) of each side, the interface terms and the
loads, and the ghost penalties of the faces between two owned cells; on the seam the ghost
penalties of the faces between an owned cell and a ghost that the rank assembles.  The unknowns are keyed
``node * 2 + side`` (:class:`~cutfem.distributed.system.GlobalNumbering`): each rank's block holds
both sides of its nodes, a permutation of the serial [inside | outside] numbering.  The Dirichlet
condition u = g on the outside field at the background's boundary nodes (those of the facets of one
tet of the whole mesh, which every rank holds: the box's faces for the slabs, the mesh's boundary
facets for the cell partition, the serial :attr:`~cutfem.fem.spaces.CutSpace.boundary_dofs`) is
the serial elimination
(:func:`cutfem.fem.terms.apply_dirichlet`) done on the assembled PETSc matrix: rows and columns
zeroed with b -= K[:, D] g (``MatZeroRowsColumns``), then the diagonal |K_ii| and b_i = |K_ii| g_i.
"""

from __future__ import annotations

import numpy as np

from ..fem.forms import assemble
from ..fem.norms import l2_h1_errors
from ..fem.spaces import CutSpace, ProductSpace
from ..fem.terms import face_jump_penalty, interface_nitsche, load, stiffness
from ..geometry.markers import NEG, POS
from ..geometry.shapes import Sphere
from ..geometry.box import StructuredBox
from ..problems.common import check_ghost_penalty, check_nitsche_penalty, levelset_for
from ..problems.interface_poisson import InterfaceSolution, LevelSetSolution
from ..runs.registry import ProblemError
from ..runs.runner import Timer
from .assembly import Piece, RankPieces, global_keys
from .launch import engine
from .levels import shared_background, solve_on_ranks

__all__ = ["interface_poisson_cut_level", "interface_pieces"]

SIDES = (NEG, POS)


def interface_pieces(cuts, a, gamma, gamma_g, weights, sol) -> RankPieces:
    """The rank's pieces of the interface system on the product space (inside, outside) of each of
    its cuts; ``a`` the coefficient of each side."""
    out = RankPieces()

    def ghost(cut, facets_of):
        form = None
        for k, side in enumerate(SIDES):
            F = facets_of(cut.ghost_facets(side))
            out.faces += F.n_facets
            if F.n_facets:
                term = a[side] * gamma_g * face_jump_penalty(cut.dF(F), h_power=1, field=k)
                form = term if form is None else form + term
        return form

    owned, seam = cuts.owned, cuts.seam
    if owned is not None:
        W = out.space = ProductSpace(CutSpace(owned, NEG), CutSpace(owned, POS))
        if W.n_dofs:
            form, rhs = None, None
            for k, side in enumerate(SIDES):
                if W[k].n_dofs:
                    dx = owned.dx(side)
                    term, f = a[side] * stiffness(dx, field=k), load(sol.f(side), dx, degree=2, field=k)
                    form, rhs = (term, f) if form is None else (form + term, rhs + f)
            if owned.n_tets:
                form = form + interface_nitsche(owned.ds(), a[NEG], a[POS], gamma, weights)
                if gamma_g > 0:
                    g = ghost(owned, lambda F: F)
                    form = form if g is None else form + g
            out.pieces.append(Piece(global_keys(W), assemble(form, W), assemble(rhs, W)))
    if seam is not None and seam.n_tets and gamma_g > 0:
        S = ProductSpace(CutSpace(seam, NEG), CutSpace(seam, POS))
        g = ghost(seam, cuts.seam_facets)
        if g is not None:
            out.pieces.append(Piece(global_keys(S), assemble(g, S)))
    return out


def _dirichlet(background, g):
    """The constraint of :func:`~cutfem.distributed.levels.solve_on_ranks`: u = g(x) on the outside
    field's unknowns at the boundary nodes of the whole ``background`` (a structured box's from its
    six faces, an unstructured mesh's from its facets of one tet), by symmetric elimination on
    PETSc with the diagonal |K_ii| kept (see the module docstring)."""

    def constrain(A, loads, numbering, parts):
        _, PETSc = engine()
        keys = numbering.owned_keys
        nodes = keys // 2
        on = (keys % 2 == 1) & np.isin(nodes, background.boundary_nodes)
        rows = numbering(keys[on]).astype(PETSc.IntType)
        at = nodes[on]  # a box's coordinates from the node indices, as its slabs compute them; a mesh's points
        values = np.asarray(g(background.node_coordinates(at) if isinstance(background, StructuredBox) else background.points[at]),
                            dtype=float)
        diagonal = np.abs(A.getDiagonal().getArray()[rows - numbering.first])
        diagonal[diagonal == 0] = 1.0
        x = A.createVecRight()
        x.set(0.0)
        x.setValues(rows, values)
        x.assemble()
        (b,) = loads
        A.zeroRowsColumns(rows, diag=1.0, x=x, b=b)  # b -= K[:, D] g, b_D = g, rows and columns of D zeroed
        d = A.getDiagonal()
        d.setValues(rows, diagonal)
        d.assemble()
        A.setDiagonal(d, addv=PETSc.InsertMode.INSERT_VALUES)
        b.setValues(rows, diagonal * values)
        b.assemble()
        for v in (x, d):
            v.destroy()

    return constrain


def interface_poisson_cut_level(spacing, a_inside, a_outside, weights, gamma, gamma_g, surface, radius, R, r, axes, box, solver,
                                background="structured", comm=None, counts=None):
    """One level of interface-poisson-cut on the ranks of ``comm`` (default: every rank): the serial
    record's errors of each side and sizes, with the engine and the number of ranks.
    ``background``: "structured", "tetwild" or a TetMesh, the same on every rank
    (:func:`~cutfem.distributed.levels.shared_background`); ``counts``: the partition by hand
    (:func:`~cutfem.distributed.partition.partition_for`)."""
    MPI, _ = engine()
    comm = MPI.COMM_WORLD if comm is None else comm
    for name, value in (("--a-inside", a_inside), ("--a-outside", a_outside)):
        if not value > 0:
            raise ProblemError(f"{name} must be positive, got {value}")
    notes = check_ghost_penalty(gamma_g) + check_nitsche_penalty(gamma)
    a = {NEG: a_inside, POS: a_outside}
    if surface == "sphere":
        phi, sol = Sphere(radius), InterfaceSolution(radius, a_inside, a_outside)
    else:
        phi = levelset_for(surface, R, r, 1.0, axes)
        sol = LevelSetSolution(phi, a_inside, a_outside)
    t = Timer()
    with t("geometry"):
        bg = shared_background(comm, phi, spacing, background, box)

    def measure(W, x):
        out = []
        for k, side in enumerate(SIDES):
            V = W[k]
            if V.n_dofs:
                l2, h1 = l2_h1_errors(V, x[W.offsets[k] : W.offsets[k + 1]], sol.solution(side), W[k].cut.dx(side))
                out += [l2 * l2, h1 * h1]
            else:
                out += [0.0, 0.0]
        return out

    keys = ("l2_error_inside", "h1_error_inside", "l2_error_outside", "h1_error_outside")
    rec = solve_on_ranks(comm, phi, bg,
                         lambda cuts: interface_pieces(cuts, a, gamma, gamma_g, weights, sol), measure, keys, solver, counts, t,
                         fields=2, constrain=_dirichlet(bg, sol.u(POS)))
    if notes:
        rec["warnings"] = notes
    return rec
