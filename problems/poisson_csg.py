"""Poisson on a domain with edges: several level sets, Dirichlet on some parts, Neumann on others
(docs/math.md §16).

-Lap u = f in Omega, u = g on the Dirichlet parts Gamma_D, n . grad u = g_N on the Neumann parts
Gamma_N.  Omega is a Boolean combination of the insides {phi_k < 0} of level sets phi_1..phi_m (the
default: the unit ball below the plane z = 0.5), its boundary made of the parts Gamma_k on
{phi_k = 0}, each with its outward normal (:mod:`cutfem.geometry.csg_cut`).  Find u_h in V_h^NEG
(P1 on the tets that meet Omega_h) with, for all v,

    (grad u, grad v)_{Omega_h} - (n . grad u, v)_{Gamma_D} - (u, n . grad v)_{Gamma_D} + (gamma / h) (u, v)_{Gamma_D}
        + gamma_g sum_{F in G_NEG} h_F ([n_F . grad u], [n_F . grad v])_F
    = (f, v)_{Omega_h} - (g, n . grad v)_{Gamma_D} + (gamma / h) (g, v)_{Gamma_D} + (g_N, v)_{Gamma_N}.

Nitsche's terms and the Neumann load are integrands over ``cut.ds(parts)`` (each triangle with its
own outward normal w.n); h is h_T of the cut tet.  Manufactured solution from sympy (:class:`cutfem.Exact`):
u = sin(pi x / 2) cos(pi y / 3) exp(z / 2), f = -Lap u, g = u, and g_N = grad u . n with n the exact
outward normal of the part's level set at the quadrature point (grad phi_k / |grad phi_k|, turned to
the side of the discrete outward normal): exact on a plane, O(h^2) from the surface's on a curved
part.  Expected: L2 error O(h^2), H1 error O(h).

The command line takes the level sets as one text, separated by ';' (``--levelsets "sphere; z -
0.5"``: each a named surface, a file or an expression in x, y, z, as ``--surface`` of poisson-cut),
the domain as text over their names phi1..phim (``--domain "phi1 & phi2"``: & intersection, |
union, - difference, ~ complement, parentheses) and the Neumann parts by those names (``--neumann
phi2``, or ``none``); every other part of the boundary is Dirichlet.
"""

from __future__ import annotations

import re

import numpy as np

from cutfem.fem.exact import Exact
from cutfem.fem.forms import assemble, bilinear_form, linear_form
from cutfem.fem.norms import l2_h1_errors
from cutfem.fem.pointwise import dot
from cutfem.fem.spaces import CutSpace
from cutfem.fem.terms import face_jump_penalty, load, stiffness
from cutfem.geometry.csg import Domain
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import NEG
from cutfem.runs.registry import H_BACKGROUND, LazyFields, Param, ProblemError, register
from cutfem.runs.runner import Timer
from cutfem.solvers.solve import solve

from .common import (finish_record, BACKGROUND_PARAM, BULK_BYTES_PER_TET, DOMAIN_BOX_PARAM, SOLVER_PARAM, USER_SURFACES, background_for, check_bulk_memory,
                     check_ghost_penalty, check_nitsche_penalty, levelset_for)

#: the manufactured solution and its data
U = Exact("sin(pi*x/2)*cos(pi*y/3)*exp(z/2)")
GRAD_U = U.grad
SOURCE = -U.laplacian


def exact_solution(x):
    """(u, grad u) at the points x (..., 3)."""
    return U(x), GRAD_U(x)


@bilinear_form(symmetric=True)
def nitsche(u, v, w):
    """The symmetric Nitsche terms of u = g on a Dirichlet part, w.n its outward normal."""
    return -dot(w.n, u.grad) * v - dot(w.n, v.grad) * u + w.gamma / w.h * u * v


@linear_form
def nitsche_load(v, w):
    """Their right-hand side: (g, gamma / h v - n . grad v), g = u."""
    return w.at(U) * (w.gamma / w.h * v - dot(w.n, v.grad))


@linear_form
def neumann_load(v, w):
    """(grad u . n, v) on a Neumann part: n the exact unit normal of its level set ``w.normal``,
    turned to the side of the outward normal w.n of the discrete part."""
    n = w.at(w.normal)
    n = n * np.sign(dot(n, w.n))[..., None]
    return v * dot(w.at(GRAD_U), n)


#: the record entries of poisson-csg-cut
DEFINITIONS = {
    "h": H_BACKGROUND,
    "l2_error": "||u_h - u||_L2(Omega_h) over the cut volume (degree-4 quadrature on its whole tets and sub-tets)",
    "h1_error": "||grad u_h - grad u||_L2(Omega_h), as l2_error",
}

LEVELSETS_HELP = ("the level sets phi1; phi2; ... separated by ';', each a named surface (sphere, of --radius; torus; "
                  f"ellipsoid), or {USER_SURFACES}; the plane z = c is 'z - c'")
DOMAIN_HELP = ("the domain over the level sets' names: & intersection, | union, - difference, ~ complement, parentheses "
               "(phiK < 0 is the inside of the K-th level set)")


def parse_levelsets(levelsets, radius=1.0) -> list:
    """The level sets of ``--levelsets``: a text with ';' between them, or a sequence of level sets
    or texts (Python)."""
    items = [s.strip() for s in levelsets.split(";")] if isinstance(levelsets, str) else list(levelsets)
    if not items or any(isinstance(s, str) and not s for s in items):
        raise ProblemError(f"--levelsets: give one or more level sets separated by ';', got {levelsets!r}")
    out = []
    for k, s in enumerate(items):
        try:
            out.append(levelset_for(s, radius=radius))
        except ProblemError as exc:
            raise ProblemError(f"--levelsets, phi{k + 1}: {exc}") from None
    return out


def parse_domain(text, levelsets) -> Domain:
    """The domain of ``--domain`` over the level sets (:meth:`cutfem.geometry.csg.Domain.from_text`)."""
    try:
        return Domain.from_text(text, levelsets)
    except ValueError as exc:
        raise ProblemError(f"--domain: {exc}") from None


def parse_parts(text, domain: Domain) -> list:
    """The numbers of the Neumann parts of ``--neumann``: names phiK separated by commas or spaces, or 'none'."""
    names = text if isinstance(text, (list, tuple)) else [n for n in re.split(r"[,\s]+", str(text).strip()) if n]
    if names in (["none"], []):
        return []
    try:
        return sorted({domain.index(n) for n in names})
    except ValueError as exc:
        raise ProblemError(f"--neumann: {exc}") from None


@register(
    "poisson-csg-cut",
    summary="Poisson on a domain of several level sets (default: the ball below z = 0.5), Nitsche on the Dirichlet parts, "
            "Neumann on others, ghost penalty (docs/math.md §16)",
    levels=[0.2, 0.1, 0.05, 0.025],
    level_name="spacing",
    definitions=DEFINITIONS,
    params=[
        Param("levelsets", str, "sphere; z - 0.5", LEVELSETS_HELP),
        Param("domain", str, "phi1 & phi2", DOMAIN_HELP),
        Param("neumann", str, "phi2", "the Neumann parts: names phiK separated by commas, or none; the other parts are "
              "Dirichlet (Nitsche)"),
        Param("radius", float, 1.0, "radius of a level set named sphere", positive=True),
        BACKGROUND_PARAM,
        DOMAIN_BOX_PARAM,
        Param("gamma", float, 10.0, "Nitsche penalty gamma (a warning above 1e3); where two Dirichlet parts meet, a tet "
              "carries two pieces and the bound about doubles: 20 (the ball above z = 0.5, all Dirichlet)", positive=True),
        Param("gamma_g", float, 0.1, "ghost penalty gamma_g (meaningful in [0.01, 1]: a warning above 1, refused above 1e6)", minimum=0),
        SOLVER_PARAM,
    ],
)
def poisson_csg_cut(spacing, levelsets, domain, neumann, radius, background, box, gamma, gamma_g, solver):
    """One level of Poisson on a domain of several level sets; see the module docstring."""
    notes = check_ghost_penalty(gamma_g) + check_nitsche_penalty(gamma)
    t = Timer()
    with t("geometry"):
        omega = parse_domain(domain, parse_levelsets(levelsets, radius))
        neumann_parts = parse_parts(neumann, omega)
        dirichlet_parts = [k for k in range(len(omega.levelsets)) if k not in neumann_parts]
        if not dirichlet_parts:
            raise ProblemError("--neumann names every part of the boundary: with Neumann data alone u is fixed only up to a "
                               "constant; leave at least one part Dirichlet")
        bg = background_for(omega, spacing, background, box)
        check_bulk_memory(bg, omega, (NEG,), BULK_BYTES_PER_TET["poisson-cut"], spacing)  # poisson-cut's fields and terms
        cut = cut_mesh(bg, omega)
        V = CutSpace(cut, NEG)
        dx, dD = cut.dx(NEG), cut.ds(dirichlet_parts)
        empty = [omega.names[k] for k in range(len(omega.levelsets)) if cut.part_area(k) == 0]
        if empty:
            raise ProblemError(f"the part(s) {', '.join(empty)} of the boundary of {omega} are empty at spacing {spacing:g}: the "
                               "level set does not bound the domain there; check --domain, or refine")
    with t("assembly"):
        a = stiffness(dx) + nitsche.on(dD, gamma=gamma)
        if gamma_g > 0:
            a = a + gamma_g * face_jump_penalty(cut.dF(cut.ghost_facets(NEG)), h_power=1)
        rhs = load(SOURCE, dx, degree=2) + nitsche_load.on(dD, gamma=gamma)
        for k in neumann_parts:
            rhs = rhs + neumann_load.on(cut.ds(k), normal=omega.levelsets[k].normal)
        K, b = assemble(a, V), assemble(rhs, V)
    with t("solve"):
        u, info = solve(K, b, method=solver, space=V, indefinite_hint=f"raise the Nitsche penalty --gamma (now {gamma:g})")
    with t("errors"):
        rec = {
            "h": V.h,
            "dofs": int(V.n_dofs),
            **dict(zip(("l2_error", "h1_error"), l2_h1_errors(V, u, exact_solution, dx))),
            "volume": dx.size,
            **{f"area_{n}": cut.part_area(k) for k, n in enumerate(omega.names)},
            "solver": info.method,
            "solver_iterations": info.iterations,
        }
    finish_record(rec, cut, V, notes, t)
    rec["fields"] = LazyFields(lambda: {"domain": V.elements.to_pyvista(u_h=u, u_exact=U(V.dof_points)), "boundary": cut.to_pyvista()})
    return rec
