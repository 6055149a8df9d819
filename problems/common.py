"""Shared set-up of the problems: surfaces by name, background boxes, timing."""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import numpy as np

from cutfem.geometry.shapes import Ellipsoid, Sphere, Torus
from cutfem.geometry.levelset import FunctionLevelSet, LevelSet
from cutfem.geometry.signed_distance import SignedDistance
from cutfem.geometry.markers import NEG, POS
from cutfem.geometry.box import structured_box
from cutfem.geometry.mesh import unique_keys, unstructured_box
from cutfem.runs.registry import Param, ProblemError
from cutfem.geometry.surface_meshes import RANDOM_FAMILIES, TORUS_FAMILIES, sphere_mesh, torus_mesh
from cutfem.geometry.surface import read_surface

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

#: the linear solvers of the problems (:func:`cutfem.solvers.solve.solve`'s methods), and their parameter
SOLVERS = ("auto", "direct", "cg-mg", "cg-amg", "cg-jacobi")
SOLVER_PARAM = Param("solver", str, "auto", "linear solver", choices=SOLVERS)
ORDER_PARAM = Param("order", int, 1, "order of the fields and the geometry: 1 (P1 on the planar cut) or 2 (P2 on the cut "
                    "lifted by Theta_h, docs/math.md §17-18)", choices=(1, 2))

#: the background box of the bulk problems
DOMAIN_BOX_PARAM = Param("box", str, None, "background box x0,y0,z0,x1,y1,z1 (default: the domain's box grown by 0.1)")

#: the domain, background and box of the bulk problems whose data do not depend on the domain
DOMAIN_PARAMS = [
    Param("surface", str, "sphere", "domain: sphere (ball), torus (solid torus), ellipsoid, a closed mesh file, an expression "
          "in x, y, z or a Python file defining phi"),
    BACKGROUND_PARAM,
    DOMAIN_BOX_PARAM,
]

#: the background box of the cut surface problems
SURFACE_BOX_PARAM = Param("box", str, None, "background box x0,y0,z0,x1,y1,z1 (default: the surface's box grown by 0.1)")

#: the family of a triangulated torus and the seed of its random families (the meshed surface problems)
TORUS_MESH_PARAMS = [
    Param("family", str, "structured", "torus mesh family", choices=TORUS_FAMILIES, only=("surface", ("torus",))),
    Param("seed", int, 0, "random seed of the flipped/perturbed families", minimum=0,
          only=(("surface", ("torus",)), ("family", RANDOM_FAMILIES))),
]


def face_stabilization_params(only=None) -> list:
    """The face stabilization tau_F h^a J_F of a cut surface field, ``tau_f`` and ``face_h_power``
    (checked by :func:`check_face_stabilization`), given only under the condition ``only`` when set
    (:class:`~cutfem.runs.registry.Param`)."""
    return [
        Param("tau_f", float, 0.1, "face stabilization tau_F (its weight tau_F (s/L)^a: a warning below 1e-3, refused below "
              "1e-6 and above 1e6 (s/L)^2)", minimum=0, only=only),
        Param("face_h_power", float, 0.0, "power a of h in the face term h^a J_F (see --tau-f)", only=only),
    ]


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
    "and optionally grad, hessian, lipschitz, box, area (cutfem.geometry.levelset.FunctionLevelSet.from_file), or an "
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


#: the meaningful range of the ghost penalty gamma_g (docs/math.md §7): g and the bulk form both
#: scale as h^3 per tet, so gamma_g is a number, the same at every spacing.  It adds about
#: gamma_g h^2 |u|_{H^2}^2 to the squared energy error (weak consistency), and as gamma_g grows it
#: locks u_h to one linear function across the ghost faces: poisson-cut's L2 error at spacings
#: 0.25 / 0.125 is 0.0264 / 0.0068 at 0.1, 0.061 / 0.018 at 1, 0.131 / 0.059 at 10, and
#: 0.266 / 0.264 from 1e4 to 1e9 (locked: the result no longer depends on gamma_g); at 1e12 the
#: solvers find the constants a null vector.  Above GHOST_PENALTY_WARN a warning, above
#: GHOST_PENALTY_MAX (locked, two decades past the onset) a refusal.
GHOST_PENALTY_WARN, GHOST_PENALTY_MAX = 1.0, 1e6
#: the meaningful range of the face stabilization of a surface field, stated for its weight
#: t = tau_F (s / L)^a (s the spacing, a the power of h, L the length scale in which the surface has
#: size about 1): the coefficient of J_F (whose entries are O(1) per face) at this spacing, in units
#: of L, to compare with the paper's 0.1 (a = 0).  The mass of a whole piece is O((s / L)^2):
#: t / (s / L)^2 is the weight of the stabilization against it.  Below FACE_WEIGHT_WARN the nodes
#: with small pieces are barely controlled and the error grows like 1 / t (mean-curvature-cut,
#: sphere, spacings 0.2 / 0.1 / 0.05: L2 error 0.061 /
#: 0.019 / 0.0056 at t = 0.1, 0.27 / 0.081 / 0.025 at 1e-3, 1.4 / 0.49 / 0.15 at 1e-4, 5.8 /
#: 5.3 / 3.8 at 1e-6): a warning; below FACE_WEIGHT_MIN the result is meaningless (O(1) errors
#: at every spacing): a refusal.  Above it the error does not
#: grow (0.051 / 0.013 / 0.0032 at t = 10 and 100), but the mass is lost beside J_F: the constants,
#: which J_F annihilates, have ||D^-1/2 K 1|| / ||D^1/2 1|| = 0.026 (s / L)^2 / t (0.025-0.026 on the
#: unit sphere at spacings 0.2-0.025, t = 0.1 and 1e4), which reaches the solvers' null-vector
#: tolerance (1e-8; CG refused tau_F = 1e4 at spacing 0.05) near t / (s / L)^2 = FACE_RATIO_MAX: a
#: refusal there.  (The paper's tau_F = 0.1 meets it only below spacing 3e-4, which no memory holds.)
FACE_WEIGHT_WARN, FACE_WEIGHT_MIN, FACE_RATIO_MAX = 1e-3, 1e-6, 1e6


#: the Nitsche penalty gamma (docs/math.md §8): gamma / h (u, v)_Gamma beside the stiffness is a
#: number.  Below its stability bound the system is indefinite (the solver says so and names
#: --gamma); far above it Nitsche's method tends to the strong condition on the cut boundary, which
#: locks on the small cut pieces: poisson-cut's L2 error at spacings 0.25 / 0.125 is 0.0264 / 0.0068
#: at 10, 0.030 / 0.0075 at 100, 0.044 / 0.011 at 1e3, 0.088 / 0.031 at 1e4, 0.15 / 0.084 at 1e6.
#: A warning above NITSCHE_WARN.
NITSCHE_WARN = 1e3
#: the normal-gradient stabilization tau_N h^a (n_h . grad u, n_h . grad v) over the cut tets
#: (docs/math.md §4): its entries are O(s^(a+1)) at spacing s, the surface mass's O(s^2) (and with
#: a = -1 against the tangential stiffness's O(1) as with a = 1 against the mass), so the weight
#: is w = tau_N (s / L)^(a - 1).  The error hardly moves below 1 (laplace-beltrami-cut, sphere,
#: spacings 0.2 / 0.1 / 0.05: L2 error 0.029 / 0.0074 / 0.0018 at 1e-6 and 0.037 / 0.0091 /
#: 0.0022 at 1) and grows above it (0.12 / 0.016 / 0.0029 at 100, 1.3 / 0.38 / 0.041 at 1e4,
#: 1.8 / 2.0 / 1.1 at 1e6: the surface terms lost beside it); at 1e-8 phi_h is numerically null
#: and at 1e9 the constants.  A warning above NORMAL_WEIGHT_WARN, a refusal above
#: NORMAL_WEIGHT_MAX and below NORMAL_WEIGHT_MIN.
NORMAL_WEIGHT_WARN, NORMAL_WEIGHT_MAX, NORMAL_WEIGHT_MIN = 100.0, 1e6, 1e-8
#: the edge stabilization tau_E of the meshed mean curvature problem (docs/math.md §3; the paper's
#: 0.1): on the flipped torus at n = 16 / 32 / 64 the L2 error is 1.6 / 0.64 / 0.21 at 0.1,
#: 4.1 / 2.3 / 1.1 at 1, 7.0 / 5.4 / 3.4 at 10 and about 9.4 (locked) from 1e4 on.  A warning above
#: EDGE_WARN.
EDGE_WARN = 1.0


def _finite_nonnegative(value, flag) -> float:
    """``value`` as a float >= 0, or ProblemError naming ``flag`` (the problem functions are also
    called directly from Python, past the checks of :class:`~cutfem.runs.registry.Param`)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ProblemError(f"{flag}: cannot read {value!r} as a number") from None
    if not (math.isfinite(v) and v >= 0):
        raise ProblemError(f"{flag}: {value!r} must be a finite number >= 0")
    return v


def _warn(message: str) -> list:
    """Issue ``message`` as a RuntimeWarning (from the problem's caller) and return it in a list,
    for the record's ``"warnings"``."""
    warnings.warn(message, RuntimeWarning, stacklevel=3)
    return [message]


def check_ghost_penalty(gamma_g, flag="--gamma-g") -> list:
    """Refuse (ProblemError) a ghost penalty gamma_g that is negative, not finite or above
    :data:`GHOST_PENALTY_MAX`; warn (RuntimeWarning) above :data:`GHOST_PENALTY_WARN`, where it
    costs accuracy.  Returns the warnings given, for the record.  gamma_g = 0 (no ghost penalty) is
    allowed: the solver then reports the loss of stability it causes."""
    g = _finite_nonnegative(gamma_g, flag)
    fit = f"use {flag} in [0.01, {GHOST_PENALTY_WARN:g}] (the default 0.1; poisson-cut at order 2: 0.01)"
    if g > GHOST_PENALTY_MAX:
        raise ProblemError(
            f"{flag} {g:g} is above {GHOST_PENALTY_MAX:g}: the ghost penalty locks u_h to one linear function across the "
            f"ghost faces and the result no longer depends on it (poisson-cut at spacing 0.25: L2 error 0.266 from 1e4 to "
            f"1e9, against 0.0264 at 0.1; at 1e12 the system is numerically singular); {fit}")
    if g > GHOST_PENALTY_WARN:
        return _warn(
            f"{flag} {g:g} is above {GHOST_PENALTY_WARN:g}: the ghost penalty's consistency error grows with it and locks "
            f"u_h toward linear functions (poisson-cut at spacing 0.25: L2 error 0.131 at 10, 0.266 at 1e6, against 0.0264 "
            f"at 0.1); {fit}")
    return []


def check_nitsche_penalty(gamma, flag="--gamma") -> list:
    """Refuse (ProblemError) a Nitsche penalty that is not a finite positive number; warn
    (RuntimeWarning) above :data:`NITSCHE_WARN`, where the method locks toward the strong condition
    on the cut pieces.  Returns the warnings given, for the record."""
    g = _finite_nonnegative(gamma, flag)
    if g == 0:
        raise ProblemError(f"{flag}: the Nitsche penalty must be positive (default 10), got {gamma!r}")
    if g > NITSCHE_WARN:
        return _warn(
            f"{flag} {g:g} is above {NITSCHE_WARN:g}: Nitsche's method then tends to the strong boundary condition on "
            f"the cut pieces, which locks (poisson-cut at spacing 0.125: L2 error 0.031 at 1e4, 0.084 at 1e6, against "
            f"0.0068 at 10); use {flag} in [10, 100] (above the stability bound, which the solver reports if not)")
    return []


def _coefficient_and_power(tau, flag, power, power_flag) -> tuple[float, float]:
    """A stabilization's coefficient (finite, >= 0) and its power of h (finite) as floats, or
    ProblemError naming the flag."""
    value = _finite_nonnegative(tau, flag)
    try:
        a = float(power)
    except (TypeError, ValueError):
        raise ProblemError(f"{power_flag}: cannot read {power!r} as a number") from None
    if not math.isfinite(a):
        raise ProblemError(f"{power_flag}: {power!r} must be a finite number")
    return value, a


def check_normal_stabilization(tau_n, normal_h_power, spacing, length_scale=1.0, flag="--tau-n",
                               power_flag="--normal-h-power", warn=True) -> list:
    """Refuse (ProblemError) or warn (RuntimeWarning) about the normal-gradient stabilization
    tau_N h^a of a surface field at the spacing ``spacing`` by its weight w = tau_N (s / L)^(a - 1)
    against the surface terms: refused below :data:`NORMAL_WEIGHT_MIN` or above
    :data:`NORMAL_WEIGHT_MAX`, a warning above :data:`NORMAL_WEIGHT_WARN` (``warn``: off for a problem
    whose exact solution extends constantly along the normals, as the mean curvature vector's: the
    term's consistency error is then that of the normal, and mean-curvature-cut's normal option takes
    tau_N h^-1, a weight growing as s^-2); tau_N = 0 (none) is left to the solver, which
    reports phi_h as a null vector.  Returns the warnings given."""
    tau, a = _coefficient_and_power(tau_n, flag, normal_h_power, power_flag)
    if tau == 0:
        return []
    s = float(spacing) / float(length_scale)
    log_w = math.log10(tau) + (a - 1.0) * math.log10(s)
    who = f"{flag} {tau:g}" + (f" with {power_flag} {a:g}" if a != 1 else "")
    weight = f"the weight tau_N (s / L)^(a - 1) = 10^{log_w:.3g} at s / L = {s:g}" if a != 1 else f"tau_N = {tau:g}"
    base = (a - 1.0) * math.log10(s)
    fit = (f"tau_N in [{_power_of_ten(math.log10(1e-2) - base)}, {_power_of_ten(math.log10(NORMAL_WEIGHT_WARN) - base)}]"
           f"{' at this power' if a != 1 else ''} (default 1 with a = 1)")
    if log_w < math.log10(NORMAL_WEIGHT_MIN):
        raise ProblemError(f"{who}: {weight} is below {NORMAL_WEIGHT_MIN:g}: the stabilization vanishes and phi_h (zero on "
                           f"S_h) is a numerical null vector; give {fit}")
    if log_w > math.log10(NORMAL_WEIGHT_MAX):
        raise ProblemError(f"{who}: {weight} is above {NORMAL_WEIGHT_MAX:g}: the surface terms are lost beside it and "
                           f"the errors are O(1) (the system numerically singular from 1e9); give {fit}")
    if warn and log_w > math.log10(NORMAL_WEIGHT_WARN):
        return _warn(f"{who}: {weight} is above {NORMAL_WEIGHT_WARN:g}: it damps the solution along the surface too "
                     f"(laplace-beltrami-cut at spacing 0.1: L2 error 0.38 at 1e4, 0.016 at 100, against 0.0091 at 1); "
                     f"give {fit}")
    return []


def check_edge_stabilization(tau_e, flag="--tau-e") -> list:
    """Refuse (ProblemError) an edge stabilization tau_E that is negative or not finite; warn
    (RuntimeWarning) above :data:`EDGE_WARN`, where it costs accuracy.  Returns the warnings given."""
    tau = _finite_nonnegative(tau_e, flag)
    if tau > EDGE_WARN:
        return _warn(f"{flag} {tau:g} is above {EDGE_WARN:g}: the edge stabilization locks H_h toward functions without "
                     f"conormal jumps (flipped torus at n = 32: L2 error 2.3 at 1, 5.4 at 10, against 0.64 at 0.1); give "
                     f"{flag} in [0.01, {EDGE_WARN:g}] (the paper: 0.1)")
    return []


def _power_of_ten(x: float) -> str:
    """10^x as text, also where the float would overflow or underflow."""
    return f"{10.0 ** x:.2g}" if abs(x) < 300 else f"10^{x:.4g}"


def check_face_stabilization(tau_f, face_h_power, spacing, length_scale=1.0, flag="--tau-f",
                             power_flag="--face-h-power") -> list:
    """Refuse (ProblemError) or warn (RuntimeWarning) about the face stabilization tau_F h^a J_F of
    a surface field at the spacing ``spacing``: its weight t = tau_F (s / L)^a must be at least
    :data:`FACE_WEIGHT_MIN` (warning below :data:`FACE_WEIGHT_WARN`) and t / (s / L)^2 at most
    :data:`FACE_RATIO_MAX`; tau_F and a finite, tau_F >= 0 (0: no stabilization, which the solver
    reports).  The messages name the flags (the power when it is not 0) and the values that fit.
    Returns the warnings given, for the record."""
    tau, a = _coefficient_and_power(tau_f, flag, face_h_power, power_flag)
    if tau == 0:
        return []
    s = float(spacing) / float(length_scale)  # the spacing in units of L, where the surface has size about 1
    log_t = math.log10(tau) + a * math.log10(s)  # in logarithms: no overflow for a = 50 or tau_F = 1e300
    log_ratio = log_t - 2.0 * math.log10(s)
    low, high = math.log10(FACE_WEIGHT_WARN), math.log10(FACE_RATIO_MAX) + 2.0 * math.log10(s)
    weight = f"the weight tau_F (s / L)^a = 10^{log_t:.3g} at s / L = {s:g}" if a else f"tau_F = {tau:g}"
    # the tau_F at this a, and the a at this tau_F, whose weight lies in [FACE_WEIGHT_WARN, FACE_RATIO_MAX (s / L)^2]
    base = a * math.log10(s)
    fit = f"tau_F in [{_power_of_ten(low - base)}, {_power_of_ten(high - base)}]" + (" at this power" if a else "")
    if a and s != 1:
        ends = sorted(((low - math.log10(tau)) / math.log10(s), (high - math.log10(tau)) / math.log10(s)))
        fit = f"{power_flag} in [{ends[0]:.3g}, {ends[1]:.3g}] at this spacing" + (f", or {fit}" if abs(base) < 300 else "")
    fit += " (the paper: tau_F = 0.1, a = 0)"
    who = f"{flag} {tau:g}" + (f" with {power_flag} {a:g}" if a else "")
    if log_t < math.log10(FACE_WEIGHT_MIN):
        raise ProblemError(
            f"{who}: {weight} is below {FACE_WEIGHT_MIN:g}: the face stabilization vanishes beside the mass of the pieces, "
            f"the nodes with small pieces are not controlled and the errors are O(1) (the system is nearly singular); "
            f"give {fit}")
    if log_ratio > math.log10(FACE_RATIO_MAX):
        raise ProblemError(
            f"{who}: {weight} is {_power_of_ten(log_ratio)} times (s / L)^2, the scale of the mass of a piece, above "
            f"{FACE_RATIO_MAX:g} times: "
            "the mass of the pieces is lost beside the face stabilization and the system is numerically singular "
            f"(the constants pass for a null vector); give {fit}")
    if log_t < low:
        return _warn(
            f"{who}: {weight} is below {FACE_WEIGHT_WARN:g}: the nodes with small pieces are barely controlled and the "
            f"error grows like 1 / tau_F (mean-curvature-cut on the sphere at spacing 0.1: L2 error 0.081 at 1e-3, 0.49 "
            f"at 1e-4, against 0.019 at 0.1); give {fit}")
    return []


#: a row of a surface system whose diagonal is at most this times the median diagonal is one that no
#: term sees (:func:`pin_unseen_nodes`)
UNSEEN_TOL = 1e-12


def pin_unseen_nodes(K, B, space):
    """(K, B, count) with the unknowns that appear in no term of a surface system fixed at 0.

    When S_h runs along faces of the background mesh (a level set zero on whole grid faces: a cube
    or a flat cap on grid planes), the piece in such a face is counted once, in the tet on one side,
    and the node of that tet opposite the face has a basis function that vanishes on S_h.  When no
    face at the node is shared by two active tets, the face stabilization does not reach it either:
    its row and column of K are zero, or round-off (1.8e-32 against a median diagonal of 0.57 for
    nodes inside a cube on grid planes at spacing 0.1, exactly 0 outside), whatever tau_F
    (cutfem.solvers.solve names this for a system solved directly).  Its value changes nothing on S_h, so
    these unknowns are removed by fixing them at 0: their rows and columns (round-off at most)
    replaced by a diagonal entry (the mean diagonal, to keep K's scale for the iterative solvers)
    and a zero right-hand side, the numbering unchanged for the multigrid.  Only rows whose
    diagonal is at most :data:`UNSEEN_TOL` times the median, at nodes off S_h (phi_h != 0), are
    fixed (what such a row adds is round-off beside the rest); any other zero row is left to the
    solver, which reports it.  K is symmetric positive semidefinite here (a sum of Gram matrices),
    so a zero diagonal entry means a zero row."""
    import scipy.sparse as sp

    d = K.diagonal()
    unseen = np.flatnonzero(d <= UNSEEN_TOL * np.median(d[d > 0])) if np.any(d > 0) else np.arange(0)
    phi = getattr(getattr(space, "cut", None), "values", None)
    if unseen.size == 0 or phi is None or np.shape(phi) != (K.shape[0],) or not np.all(phi[unseen] != 0):
        return K, B, 0
    keep, pin = np.ones(K.shape[0]), np.zeros(K.shape[0])
    keep[unseen], pin[unseen] = 0.0, d[d > 0].mean()
    B = np.array(B, dtype=float)
    B[unseen] = 0.0
    D = sp.diags(keep)
    return (D @ K @ D + sp.diags(pin)).tocsr(), B, int(unseen.size)


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
    every spacing; :func:`background_for` (:func:`cutfem.geometry.box.structured_box`) grows it symmetrically
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
    grown symmetrically to the next whole number (:func:`cutfem.geometry.box.structured_box`); the record of
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
BULK_BYTES_PER_TET = {"poisson-cut": 170, "interface-poisson-cut": 170, "bulk-surface-cut": 380, "stokes-cut": 1400, "elasticity-cut": 900}
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
    :func:`cutfem.geometry.cut.cut_mesh` (``solve_bytes_per_tet``), which refuses such a spacing before the
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


def finish_record(rec: dict, cut, space=None, notes=(), timer=None) -> dict:
    """The common end of a level's record, in place: the cut's sizes (:func:`cut_record`), the
    parameter warnings when there are any, and the stage times of ``timer``."""
    rec.update(cut_record(cut, space))
    if notes:
        rec["warnings"] = notes
    if timer is not None:
        rec["time"] = dict(timer)
    return rec


def active_tets(cut, space=None) -> int:
    """The background tets that carry unknowns of ``space``: the union over the fields of a product
    space (one field's tets are distinct already, and are not sorted again: at millions of tets the
    sort's copies were the largest arrays of a distributed level's end); without a space, or for
    trace fields, the cut tets."""
    fields = getattr(space, "fields", None) or ([space] if space is not None else [])
    ids = [f.elements.tet_ids for f in fields if getattr(getattr(f, "elements", None), "tet_ids", None) is not None]
    return int((len(ids[0]) if len(ids) == 1 else len(unique_keys(np.concatenate(ids)))) if ids else cut.n_tets)


def cut_record(cut, space=None) -> dict:
    """Sizes of a cut for the per-level records (and the box used, for a structured background):
    ``pieces`` the tets the surface cuts (one piece of S_h each), ``active_tets`` the background tets
    that carry unknowns of ``space`` (the union over the fields of a product space; without a space,
    or for trace fields, the cut tets)."""
    bg = cut.background
    box = {"box": [bg.lower.tolist(), bg.upper.tolist()]} if hasattr(bg, "lower") else {}
    return box | {
        "background_nodes": int(cut.background.n_used_points),
        "active_tets": active_tets(cut, space),
        "pieces": int(cut.n_tets),
        "surface_triangles": int(cut.n_triangles),
        "interior_faces": int(cut.interior_facets().n_facets),
    }


def with_point_data(dataset, **arrays):
    """``dataset`` (a pyvista mesh) with the given per-point arrays attached; returns it."""
    for name, values in arrays.items():
        dataset.point_data[name] = np.asarray(values)
    return dataset
