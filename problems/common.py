"""Shared set-up of the problems: surfaces by name, background boxes, timing."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from cutfem.levelset import Ellipsoid, FunctionLevelSet, LevelSet, SignedDistance, Sphere, Torus
from cutfem.markers import NEG, POS
from cutfem.mesh import structured_box, unique_keys, unstructured_box
from cutfem.registry import Param, ProblemError, Timer  # noqa: F401  (Timer re-exported for the problems)
from cutfem.surface import TORUS_FAMILIES, read_surface, sphere_mesh, torus_mesh

SURFACES = ("torus", "sphere", "ellipsoid")

#: the shape parameters shared by every problem
SHAPE_PARAMS = [
    Param("R", float, 1.0, "torus: radius of the big circle", positive=True, only=("surface", ("torus",))),
    Param("r", float, 0.5, "torus: radius of the tube", positive=True, only=("surface", ("torus",))),
    Param("radius", float, 1.0, "sphere radius", positive=True, only=("surface", ("sphere",))),
    Param("axes", str, "1.0,0.8,0.6", "ellipsoid semi-axes a,b,c", only=("surface", ("ellipsoid",))),
]

#: the background of the cut problems (one definition for all of them)
BACKGROUND_PARAM = Param("background", str, "structured",
                         "background mesh: structured (Kuhn cells of the given spacing) or tetwild (pytetwild, "
                         "unstructured, target edge length = spacing; its meshing dominates the run: 9-25 s at "
                         "spacing 0.1 and 2 minutes at 0.05 on 2 cores)", choices=("structured", "tetwild"))


def point_rows(x):
    """(x as a float array (..., 3), its points as C-contiguous rows (n, 3)): what the compiled
    manufactured solutions loop over; a ValueError for any other shape."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 0 or x.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., 3), got {x.shape}")
    return x, np.ascontiguousarray(x.reshape(-1, 3))


def value_and_gradient(kernel, x, *params, gradient=True):
    """(u (...), grad u (..., 3), or None without ``gradient``) at the points x (..., 3) of a compiled
    manufactured solution ``kernel(points (n, 3), *params, u (n,), grad (n or 0, 3))``, which fills
    grad only when it has rows."""
    x, pts = point_rows(x)
    u, grad = np.empty(len(pts)), np.empty((len(pts) if gradient else 0, 3))
    kernel(pts, *params, u, grad)
    return u.reshape(x.shape[:-1]), grad.reshape(x.shape) if gradient else None


def parse_numbers(text, count, flag):
    """``count`` floats from "a,b,c" or from a sequence (nested ones flattened: a box as two
    corners ((x0, y0, z0), (x1, y1, z1))); ProblemError naming ``flag`` otherwise."""
    if isinstance(text, (list, tuple, np.ndarray)):
        try:
            values = [float(v) for v in np.asarray(text, dtype=float).ravel()]
        except (TypeError, ValueError):
            raise ProblemError(f"{flag}: expected {count} numbers, got {text!r}") from None
    else:
        try:
            values = [float(v) for v in str(text).replace(" ", "").split(",") if v]
        except ValueError:
            raise ProblemError(f"{flag}: expected {count} comma-separated numbers, got {text!r}") from None
    if len(values) != count:
        raise ProblemError(f"{flag}: expected {count} comma-separated numbers, got {text!r}")
    return values


def is_file(surface) -> bool:
    return isinstance(surface, (str, Path)) and str(surface) not in SURFACES


#: how a user surface is given (the help of --surface and the error for a surface not understood)
USER_SURFACES = (
    "a closed mesh file (STL, OBJ, PLY, VTK, ...: signed distance), a Python file NAME.py defining phi(x) "
    "and optionally grad, hessian, lipschitz, box, area (cutfem.levelset.FunctionLevelSet.from_file), or an "
    "expression in x, y, z such as 'x**4 - 5*x**2 + y**4 - 5*y**2 + z**4 - 5*z**2 + 11.8' "
    "(numpy functions sin, cos, exp, sqrt, ...; FunctionLevelSet.from_expression)"
)


def _shorten(text: str, limit: int = 80) -> str:
    """``text`` for a message: its first and last characters around '...' when longer than ``limit``."""
    return text if len(text) <= limit else f"{text[:limit // 2]}...{text[-limit // 4:]} ({len(text)} characters)"


def levelset_for(surface, R=1.0, r=0.5, radius=1.0, axes="1.0,0.8,0.6") -> LevelSet:
    """The level set of ``surface``.

    ``surface`` is a LevelSet (used as is), a callable phi(x) of points (..., 3) (a FunctionLevelSet,
    derivatives by differences), a named surface (``torus``, ``sphere``, ``ellipsoid`` with the shape
    parameters), a Python file ``*.py`` (:meth:`FunctionLevelSet.from_file`), an existing closed mesh
    file (signed distance), or else a text expression in x, y, z (:meth:`FunctionLevelSet.from_expression`).
    ProblemError names the choices when none fits.
    """
    if isinstance(surface, LevelSet):
        return surface
    if callable(surface):
        return FunctionLevelSet(surface)
    if surface == "torus":
        if not 0 < r < R:
            raise ProblemError(f"torus needs 0 < r < R, got R={R}, r={r}")
        return Torus(R=R, r=r)
    if surface == "sphere":
        return Sphere(radius=radius)
    if surface == "ellipsoid":
        semi_axes = parse_numbers(axes, 3, "--axes")
        try:
            return Ellipsoid(*semi_axes)
        except ValueError as exc:
            raise ProblemError(f"--axes {axes}: {exc}") from None
    if isinstance(surface, str) and not surface.strip():  # Path("") is the current folder
        raise ProblemError(f"--surface is empty; give a named surface ({', '.join(SURFACES)}) or {USER_SURFACES}")
    path = Path(surface)
    if path.suffix == ".py":
        try:
            return FunctionLevelSet.from_file(path)
        except ValueError as exc:
            raise ProblemError(f"--surface: {exc}") from exc
    try:
        exists = path.exists()
    except OSError:  # an expression longer than a file name can be
        exists = False
    if exists:
        return SignedDistance(read_surface(path))
    if re.fullmatch(r"[\w./\\~-]*\.[A-Za-z][A-Za-z0-9]*", str(surface)):  # a file name, not an expression
        raise ProblemError(f"--surface: there is no file {str(surface)!r} (looked in {str(Path.cwd())!r}); give the path "
                           f"of an existing file, a named surface ({', '.join(SURFACES)}) or an expression in x, y, z")
    try:
        return FunctionLevelSet.from_expression(str(surface))
    except ValueError as exc:
        raise ProblemError(
            f"--surface: {_shorten(str(surface))!r} is none of {', '.join(SURFACES)}, an existing file, or a valid expression "
            f"({exc}); give a named surface or {USER_SURFACES}"
        ) from None


def nitsche_hint(gamma: float, gamma_g: float) -> str:
    """The advice for an indefinite Nitsche system (:func:`cutfem.solve.solve`'s ``indefinite_hint``):
    the penalty ``gamma`` is below its stability bound, which holds uniformly in the cut only with
    the ghost penalty; with ``gamma_g`` = 0 the bound grows without limit on small cut elements."""
    hint = f"raise the Nitsche penalty (--gamma {gamma:g} is below its stability bound)"
    if gamma_g == 0:
        hint += (" or restore the ghost penalty (--gamma-g is 0: without it the bound grows without limit on the "
                 "small cut elements, default --gamma-g 0.1)")
    return hint


def has_exact(levelset) -> bool:
    """Whether the exact closest point and mean curvature vector are available: every level set with a
    Hessian (closed forms for the named surfaces, Newton's projection and the formula of docs/math.md §1
    otherwise), not the distance to a triangle mesh (no curvature)."""
    return not isinstance(levelset, SignedDistance) and type(levelset).hessian is not LevelSet.hessian


#: a spacing below this fraction of a surface mesh's median edge length resolves its facets
#: (:func:`mesh_file_notes`)
FACET_FRACTION = 0.5


def mesh_file_notes(levelset, spacing=None, errors: str = "l2_error") -> list:
    """The notes (record ``notes``, printed under the table) of a surface read from a mesh file
    (the distance to a triangle mesh); [] for other level sets.

    The distance to a polyhedron has no curvature, so the run has no ``errors`` column: said, not
    silently left out.  And at a ``spacing`` below :data:`FACET_FRACTION` times the mesh's median
    edge length e the cut resolves the flat facets: H_h then tends to the polyhedron's curvature,
    concentrated on its edges and corners, not to that of the smooth surface the facets stand for,
    and the error against that surface grows as the spacing drops.  Measured with a 48 x 48 UV
    sphere mesh (e = 0.074) against the unit sphere's H: L2 errors 0.068, 0.032, 0.019, 0.018,
    0.024, 0.070 at spacings 0.2, 0.1, 0.05, 0.0375, 0.025, 0.0125, smallest near e / 2.  A note,
    not a refusal: the polyhedron may be the intended geometry (a CAD part with flat faces), and
    then the run is right."""
    mesh = getattr(levelset, "mesh", None) if isinstance(levelset, SignedDistance) else None
    if mesh is None:
        return []
    notes = [f"no {errors} column: a surface read from a mesh file has no exact mean curvature (the distance to "
             "a polyhedron has none); give the surface as an expression or a Python file defining phi to get errors"]
    if spacing is not None:
        tri, pts = np.asarray(mesh.triangles), np.asarray(mesh.points)
        edge = float(np.median(np.linalg.norm(pts[tri] - pts[np.roll(tri, 1, axis=1)], axis=-1)))
        if spacing < FACET_FRACTION * edge:
            notes.append(
                f"spacing {spacing:g} is below {FACET_FRACTION:g} times the facet size of the surface mesh (median edge "
                f"{edge:.3g}): the cut resolves its flat facets, and H_h tends to the curvature of the polyhedron "
                "(concentrated on its edges) instead of the smooth surface's; the error against the smooth surface grows "
                "as the spacing drops (a 48 x 48 sphere mesh, median edge 0.074: 0.018 at spacing 0.0375, 0.070 at "
                f"0.0125). Use spacing >= {FACET_FRACTION * edge:.2g}, a surface mesh with edges below 2 x spacing, or "
                "the surface itself (expression or Python file)")
    return notes


def sphere_refinements(n) -> int:
    """L = round(log2(n / 5)), at least 0: the refinements of the icosahedron that the meshed sphere
    of level n is (about n edges around a great circle, 10 * 4^L + 2 nodes)."""
    return max(0, int(round(math.log2(max(n, 1) / 5.0))))


def check_sphere_levels(levels):
    """Refuse (ProblemError) sphere levels n that round to the same icosahedron (16 and 20 both give
    L = 2): two equal rows under two names, and no rate between them."""
    seen = {}
    for n in levels:
        L = sphere_refinements(n)
        if L in seen:
            raise ProblemError(f"--n {seen[L]} and {n} give the same sphere mesh (the icosahedron refined {L} times, "
                               f"{10 * 4**L + 2} nodes): the sphere's n is rounded to 5 * 2^L; give levels that differ "
                               "by a factor 2, e.g. 10 20 40 80")
        seen[L] = n
    return levels


def surface_mesh_for(surface, n, family="structured", seed=0, R=1.0, r=0.5, radius=1.0):
    """(SurfaceMesh, level set or None) of a meshed surface at resolution ``n``.

    torus: the n x n/2 grid of docs/math.md §6.1 in the given family; sphere: an icosahedron refined
    L = round(log2(n / 5)) times (about n edges around a great circle); a file: read as is.
    """
    if surface == "torus":
        if family not in TORUS_FAMILIES:
            raise ProblemError(f"--family: {family!r} is not one of {', '.join(TORUS_FAMILIES)}")
        check_surface_memory(n * (n // 2), f"the meshed torus at n = {n} ({n * (n // 2)} nodes)")
        return torus_mesh(int(n), family=family, R=R, r=r, seed=seed), Torus(R=R, r=r)
    if surface == "sphere":
        level = sphere_refinements(n)
        check_surface_memory(10 * 4**level + 2, f"the sphere mesh at n = {n} ({10 * 4**level + 2} nodes)")
        return sphere_mesh(level, radius=radius), Sphere(radius=radius)
    if surface in SURFACES:
        raise ProblemError(f"--surface {surface} has no surface mesh generator; use torus, sphere or a mesh file")
    path = Path(surface)
    if not path.exists():
        raise ProblemError(f"--surface: {surface!r} is neither torus, sphere nor an existing mesh file")
    return read_surface(path), None


def box_for(levelset, spacing, box=None, anchored=False):
    """The background box: given as 'x0,y0,z0,x1,y1,z1', or the surface's bounding box grown by
    0.1 (the paper's margin: the paper's box [-1.6,1.6]^2 x [-0.6,0.6] for the torus), the same at
    every spacing; :func:`background_for` (:func:`cutfem.mesh.structured_box`) grows it symmetrically
    to whole cells where the spacing does not divide it.

    Choice: the box does not follow the spacing.  Rounded outward to multiples of each spacing, it
    changed between levels (the unit sphere's [-1.2,1.2]^3 at spacing 0.2, [-1.1,1.1]^3 at 0.1)
    while the rates are taken against h = N**(-1/3), which measures the spacing only in one box:
    poisson-cut's first rate read 2.47 where the error fell by 4.10 for a halved spacing.

    ``anchored=True`` rounds the grown box outward to multiples of the spacing instead, so that the
    grid's nodes lie at multiples of it, fixed in space: for a surface moved against the grid (the
    studies of random positions), where the box must not move with the surface."""
    if box is not None:
        v = parse_numbers(box, 6, "--box")
        lo, hi = np.array(v[:3]), np.array(v[3:])
        if not (np.all(np.isfinite(v)) and np.all(hi > lo)):
            raise ProblemError(f"--box: need finite x0,y0,z0,x1,y1,z1 with x1 > x0, y1 > y0, z1 > z0; got {box!r}")
        return lo, hi
    b = levelset.bounds() if hasattr(levelset, "bounds") else None
    if b is None:
        raise ProblemError(
            f"the surface {levelset!r} has no known bounding box: give the background box, --box x0,y0,z0,x1,y1,z1 "
            "(box='x0,y0,z0,x1,y1,z1' in cutfem.run), or a box containing the surface (box = (x0, y0, z0, x1, y1, z1) "
            "in a surface file, bounds= of FunctionLevelSet)"
        )
    lo, hi = np.asarray(b[0], float) - 0.1, np.asarray(b[1], float) + 0.1
    if anchored:
        lo = np.floor(lo / spacing + 1e-9) * spacing
        hi = np.ceil(hi / spacing - 1e-9) * spacing
    return lo, hi


def background_for(levelset, spacing, kind="structured", box=None, anchored=False):
    """Structured (Kuhn) or unstructured (pytetwild, target edge length = spacing) background mesh
    of the box :func:`box_for` (``anchored`` there).

    The structured mesh has exactly the given spacing: a box that is not a whole number of cells is
    grown symmetrically to the next whole number (:func:`cutfem.mesh.structured_box`); the record of
    the level keeps the box used (:func:`cut_record`)."""
    lo, hi = box_for(levelset, spacing, box, anchored)
    if kind == "structured":
        return structured_box(lo, hi, spacing=spacing)
    if kind == "tetwild":
        return unstructured_box(lo, hi, edge_length=spacing)
    raise ProblemError(f"--background: {kind!r} is not one of structured, tetwild")


def check_resolution(cut, levelset, spacing) -> None:
    """Refuse a cut that does not resolve the surface: S_h must have the Euler characteristic of
    the exact surface (2 for spheres and ellipsoids, 0 for tori) and, where the exact area is known,
    an area within 25 % of it.  Raises ProblemError naming the spacing and the fix."""
    expected = {Sphere: 2, Ellipsoid: 2, Torus: 0}.get(type(levelset))
    chi = cut.euler_characteristic
    problems = []
    if expected is not None and chi != expected:
        problems.append(f"S_h has Euler characteristic {chi}, the surface {expected}")
    area = getattr(levelset, "area", None)
    if area and abs(cut.area - area) > 0.25 * area:
        problems.append(f"the area of S_h is {cut.area:.4g}, the surface's {area:.4g}")
    if problems:
        raise ProblemError(
            f"spacing {spacing:g} is too coarse to resolve the surface ({'; '.join(problems)}); use a smaller spacing"
        )


#: the resident memory the bulk problems add per active tet of their fields (the element sets,
#: faces, matrices, solve and errors; measured peaks less the process's start, through ``cutfem
#: run``): poisson-cut on the solid torus 199, 163 and 149 bytes at spacings 0.025, 0.0125 and 0.01;
#: interface-poisson-cut 206 and 158 at 0.025 and 0.0125; bulk-surface-cut 604 and 364 at 0.025 and
#: 0.0125 (its surface field and coupling on few tets)
#: (the finer levels' figures, with the margin of the predicted active tets on top: the estimate is
#: 1.17-1.35 times the measured peak at spacing 0.01-0.0125)
BULK_BYTES_PER_TET = {"poisson-cut": 170, "interface-poisson-cut": 170, "bulk-surface-cut": 380}
#: the box-sized arrays of a side's element set (the level set at every node, the per-tet counts
#: and marks), bytes per background tet
BOX_BYTES_PER_TET = 4
#: points per axis of the sample that estimates the fraction of the box on each side
SIDE_SAMPLE = 48


def check_bulk_memory(background, levelset, sides, bytes_per_tet: float, spacing: float) -> None:
    """Refuse, before the cut, a bulk problem whose fields cannot fit in memory
    (:class:`cutfem.memory.InsufficientMemoryError` naming a spacing that fits).

    The active tets of the fields on ``sides`` (NEG, POS, or both) are predicted from the fraction
    of the box on those sides, sampled at the centres of a SIDE_SAMPLE^3 grid of the box (the whole
    box for both sides), times :data:`cutfem.memory.ACTIVE_TETS_MARGIN`; the estimate is
    :data:`cutfem.memory.SOLVE_BASE_BYTES` + ``bytes_per_tet`` per active tet (the problem's
    measured cost, :data:`BULK_BYTES_PER_TET`) + :data:`BOX_BYTES_PER_TET` per tet of the box.  Both
    scale like spacing**-3.  Backgrounds other than a structured box are made at their size already
    and not checked here."""
    from cutfem import memory

    if not hasattr(background, "n_tets") or not hasattr(background, "lower"):
        return
    box_tets = float(background.n_tets)
    if set(sides) >= {NEG, POS}:
        fraction = 1.0
    else:
        lo, hi = np.asarray(background.lower, float), np.asarray(background.upper, float)
        t = (np.arange(SIDE_SAMPLE) + 0.5) / SIDE_SAMPLE
        grid = np.stack(np.meshgrid(*(lo[k] + (hi[k] - lo[k]) * t for k in range(3)), indexing="ij"), axis=-1).reshape(-1, 3)
        values = np.asarray(levelset.value(grid), dtype=float)
        fraction = float(np.mean(values < 0)) if NEG in sides else float(np.mean(values > 0))
        fraction = min(1.0, fraction + 1.0 / SIDE_SAMPLE)  # the cut tets, and the sample's resolution
    tets = memory.ACTIVE_TETS_MARGIN * fraction * box_tets

    def model(t):  # the estimate at t times the spacing
        return memory.SOLVE_BASE_BYTES + (bytes_per_tet * tets + BOX_BYTES_PER_TET * box_tets) / t**3

    estimate = model(1.0)
    if estimate <= memory.available_memory()[0]:
        return
    fix = memory.coarser_spacing_fix(model, spacing, memory.available_memory()[0])
    memory.check_memory(estimate, f"the fields of about {tets:.3g} active tets (spacing {spacing:g}, a box of {box_tets:.3g} tets)", fix)


def check_cut_memory(cut, bytes_per_tet: float | None = None, spacing: float | None = None) -> None:
    """Refuse, before the space and the matrices are built, a cut whose later stages cannot fit:
    :data:`cutfem.memory.SOLVE_BASE_BYTES` plus ``bytes_per_tet`` per active tet (the problem's
    measured cost; default :data:`cutfem.memory.BYTES_PER_ACTIVE_TET`): what the space, faces,
    matrices, solve and errors add to the memory in use after the cut, against
    :func:`cutfem.memory.available_memory`.

    The refusal names a spacing at which this check passes: the active tets scale like
    spacing**-2 from ``spacing`` (default: the structured background's), times
    :data:`cutfem.memory.ACTIVE_TETS_MARGIN`, and the fixed part does not scale
    (:func:`cutfem.memory.spacing_that_fits`).  The problems also give their cost to
    :func:`cutfem.cut.cut_mesh` (``solve_bytes_per_tet``), which refuses such a spacing before the
    cut from the active tets it predicts; this check on the real ones catches the rest (a level set
    without a Lipschitz bound, an unstructured background)."""
    from cutfem import memory

    per_tet = memory.BYTES_PER_ACTIVE_TET if bytes_per_tet is None else bytes_per_tet
    tets = float(cut.n_tets)
    estimate = memory.SOLVE_BASE_BYTES + per_tet * tets
    available = memory.available_memory()[0]
    if estimate <= available:
        return
    if spacing is None and hasattr(cut.background, "spacing"):
        spacing = float(np.max(cut.background.spacing))
    if spacing is None:
        fix = "use a coarser spacing (the memory grows like spacing**-2)"
    else:
        model = lambda t: memory.SOLVE_BASE_BYTES + per_tet * memory.ACTIVE_TETS_MARGIN * tets / t**2  # noqa: E731
        fix = memory.coarser_spacing_fix(model, spacing, available)
    memory.check_memory(estimate, f"the matrices and the solve of {cut.n_tets} active tets", fix)


def check_surface_memory(nodes: float, what: str) -> None:
    """Refuse a meshed surface problem of ``nodes`` nodes that cannot fit
    (:data:`cutfem.memory.BYTES_PER_SURFACE_NODE` bytes per node), before the mesh is made."""
    from cutfem.memory import BYTES_PER_SURFACE_NODE, check_memory

    check_memory(BYTES_PER_SURFACE_NODE * float(nodes), what, "use a smaller n (the memory grows like n**2)")


def cut_record(cut, space=None) -> dict:
    """Sizes of a cut for the per-level records (and the box used, for a structured background):
    ``pieces`` the tets the surface cuts (one piece of S_h each), ``active_tets`` the background tets
    that carry unknowns of ``space`` (the union over the fields of a product space; without a space,
    or for trace fields, the cut tets)."""
    bg = cut.background
    box = {"box": [bg.lower.tolist(), bg.upper.tolist()]} if hasattr(bg, "lower") else {}
    fields = getattr(space, "fields", None) or ([space] if space is not None else [])
    ids = [f.elements.tet_ids for f in fields if getattr(getattr(f, "elements", None), "tet_ids", None) is not None]
    active = (len(ids[0]) if len(ids) == 1 else len(unique_keys(np.concatenate(ids)))) if ids else int(cut.n_tets)
    return box | {
        "background_nodes": int(cut.background.n_used_points),
        "active_tets": int(active),
        "pieces": int(cut.n_tets),
        "surface_triangles": int(cut.n_triangles),
        "interior_faces": int(cut.interior_facets().n_facets),
    }


def with_point_data(dataset, **arrays):
    """``dataset`` (a pyvista mesh) with the given per-point arrays attached; returns it."""
    for name, values in arrays.items():
        dataset.point_data[name] = np.asarray(values)
    return dataset
