"""Level-set descriptions of closed surfaces and their exact geometric data.

A closed surface S in R^3 is the zero set of a function phi: R^3 -> R with the sign convention of
docs/math.md §1:

* phi < 0 inside, phi > 0 outside;
* outward unit normal n = grad phi / |grad phi|;
* mean curvature (sum of the principal curvatures) k1 + k2 = div n = trace(P Hess phi) / |grad phi|,
  P = I - n n^T, so that a sphere of radius R has k1 + k2 = 2/R;
* mean curvature vector H = (k1 + k2) n (points outward on a sphere);
* closest-point map p(x) in S; the exact fields used to measure errors are extended constantly
  along normals: H^e(x) = H(p(x)), n^e(x) = n(p(x)).  For any smooth level set (distance or not)
  p(x) is found by Newton's method on the closest-point system (:meth:`LevelSet.closest_point`)
  and H(p) from the formula above; the named surfaces have closed forms.

Every point argument is an array of shape (..., 3); scalar results have shape (...), vector results
(..., 3) and matrix results (..., 3, 3).  Lengths are in the units of the coordinates.

Classes
-------
LevelSet          base class (normal, curvature and exact-field machinery on top of value/gradient/hessian)
Sphere            signed distance |x - c| - R
Torus             signed distance to a ring torus with axis z
Ellipsoid         the quadratic (x/a)^2 + (y/b)^2 + (z/c)^2 - 1 (not a distance)
FunctionLevelSet  user callables, a text expression in x, y, z, or a Python file; derivatives by
                  central differences when not given
SignedDistance    signed distance to a closed triangle mesh (a compiled nearest-triangle search)

and the function :func:`interpolate` (nodal values of a level set, with a finiteness check).
"""

from __future__ import annotations

import numpy as np

from .keys import unique_keys
from .surface import SurfaceMesh, check_length, positive_number
from . import levelset_kernels

__all__ = [
    "LevelSet",
    "Sphere",
    "Torus",
    "Ellipsoid",
    "FunctionLevelSet",
    "SignedDistance",
    "interpolate",
]

_EPS = np.finfo(float).eps

#: points per chunk of :meth:`LevelSet.closest_point`: each chunk's Newton iteration runs on its own,
#: with difference stencils of 25 points per point (a few MB) that stay in cache
NEWTON_CHUNK = 1 << 14


# ----------------------------------------------------------------------------------------------
# input checking helpers
# ----------------------------------------------------------------------------------------------
def _as_points(x, name: str = "x") -> np.ndarray:
    """Return ``x`` as a float array of shape (..., 3); ValueError if the shape or values are bad."""
    arr = np.asarray(x, dtype=float)
    if arr.ndim == 0 or arr.shape[-1] != 3:
        raise ValueError(
            f"{name} must be an array of points with shape (..., 3), got shape {arr.shape}; "
            "pass 3D coordinates along the last axis"
        )
    if not np.all(np.isfinite(arr)):
        bad = ~np.all(np.isfinite(arr), axis=-1)
        first = arr[bad][0]
        raise ValueError(
            f"{name} contains {int(bad.sum())} point(s) with NaN or infinite coordinates "
            f"(first: {first}); remove or fix them before evaluating the level set"
        )
    return arr


def _raise_if_singular(mask: np.ndarray, x: np.ndarray, what: str, where: str) -> None:
    """Raise ValueError naming the count and first point of ``x`` where ``mask`` is true."""
    if np.any(mask):
        first = x[mask][0]
        raise ValueError(
            f"{what} is undefined at {int(np.count_nonzero(mask))} point(s) {where} "
            f"(first: {first}); evaluate it only away from that set (e.g. near the surface)"
        )


def _center(center) -> np.ndarray:
    """Return ``center`` as a float array of shape (3,), ValueError otherwise."""
    c = np.asarray(center, dtype=float)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise ValueError(f"center must be 3 finite coordinates, got {center!r}")
    return c


def _positive_definite_3x3(m: np.ndarray) -> np.ndarray:
    """Whether each symmetric matrix of m (k, 3, 3) is positive definite (Sylvester's criterion:
    the three leading principal minors are positive), shape (k,)."""
    a, b, c = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    d, e, f = m[:, 1, 1], m[:, 1, 2], m[:, 2, 2]
    minor2 = a * d - b * b
    det = a * (d * f - e * e) - b * (b * f - e * c) + c * (b * e - d * c)
    return (a > 0) & (minor2 > 0) & (det > 0)


def _batched_solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve a[k] d[k] = b[k] for (m, 4, 4) matrices and (m, 4) right-hand sides in one call; rows
    whose matrix is singular or not finite get NaN (the caller treats them as failed)."""
    out = np.full(b.shape, np.nan)
    good = np.all(np.isfinite(a), axis=(-2, -1)) & np.all(np.isfinite(b), axis=-1)
    try:
        out[good] = np.linalg.solve(a[good], b[good][..., None])[..., 0]
    except np.linalg.LinAlgError:  # some matrix is exactly singular: find them, solve the others
        with np.errstate(all="ignore"):
            good &= np.linalg.cond(np.where(good[:, None, None], a, np.eye(a.shape[-1]))) < 1.0 / _EPS
        out[good] = np.linalg.solve(a[good], b[good][..., None])[..., 0]
    return out


def _as_bounds(bounds, name: str):
    """(lower (3,), upper (3,)) from a pair of 3-vectors or six numbers x0, y0, z0, x1, y1, z1."""
    try:
        arr = np.asarray(bounds, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        arr = np.zeros(0)
    if arr.size != 6 or not np.all(np.isfinite(arr)) or not np.all(arr[:3] < arr[3:]):
        raise ValueError(
            f"{name} must be a box (lower, upper) or six numbers x0, y0, z0, x1, y1, z1 with "
            f"x0 < x1, y0 < y1, z0 < z1, got {bounds!r}"
        )
    return arr[:3].copy(), arr[3:].copy()


def _shape_message(name: str, got: tuple, xshape: tuple, expected: tuple) -> str:
    """The error for a user callable ``name`` that returned shape ``got`` instead of ``expected``."""
    lead = xshape[:-1]
    if got == ():
        hint = ("it returned one number for all the points: it is written for a single point (math "
                "functions, float(), a loop); use numpy on whole arrays, e.g. np.sqrt(x[..., 0]**2 + ...)")
    elif got == expected + (1,):
        hint = "it has an extra trailing axis of length 1: drop keepdims=True, or return out[..., 0]"
    elif len(got) >= 1 and got[0] == 3 and got[1:] == lead:
        hint = ("the components are along the first axis: stack them along the last one, "
                "np.stack([gx, gy, gz], axis=-1)")
    elif len(got) >= 1 and got[0] == 3 and (len(lead) == 0 or lead[0] != 3):
        hint = ("x[0], x[1], x[2] are the first three POINTS, not the coordinates: write x[..., 0], "
                "x[..., 1], x[..., 2]")
    elif got == xshape and expected == lead:
        hint = "it returned one value per coordinate: reduce over the last axis, e.g. np.sum(x**2, axis=-1)"
    else:
        hint = ("write it vectorized over the leading axes (there may be several: the differences call "
                "it on shape (..., k, 3)), with x[..., 0] and reductions along axis=-1")
    return (f"{name}(x) returned shape {got} for points x of shape {xshape}; it must return shape "
            f"{expected}: {hint}")


#: numpy functions allowed in a text expression (FunctionLevelSet.from_expression)
_EXPRESSION_FUNCTIONS = {
    name: getattr(np, name)
    for name in ("sin", "cos", "tan", "arcsin", "arccos", "arctan", "arctan2", "sinh", "cosh", "tanh",
                 "exp", "log", "log2", "log10", "sqrt", "cbrt", "abs", "hypot", "minimum", "maximum")
}
#: the number of arguments of each function: numpy reads one more as the array to write into
_EXPRESSION_ARITY = {name: 2 if name in ("arctan2", "hypot", "minimum", "maximum") else 1 for name in _EXPRESSION_FUNCTIONS}
_EXPRESSION_CONSTANTS = {"pi": np.pi, "e": np.e}
_EXPRESSION_MAX_LENGTH = 10000


def _integer_power(a, n: int):
    """a**n for an integer 2 <= n <= 16 by repeated squaring (a few multiplications instead of the
    much slower general pow; the result differs from pow by a few ulp at most)."""
    result, base = None, a
    while n:
        if n & 1:
            result = base if result is None else result * base
        n >>= 1
        if n:
            base = base * base
    return result


def _integer_powers_transformer():
    import ast

    class IntegerPowers(ast.NodeTransformer):
        """Rewrite ``a ** n`` with an integer literal 2 <= n <= 16 into ``_integer_power(a, n)``; every
        other integer literal becomes a float, so that the constants are computed in floating point
        ('9**9**9' overflows at once instead of building a 370-million-digit integer)."""

        def visit_BinOp(self, node):
            exponent = node.right
            if isinstance(node.op, ast.Pow) and isinstance(exponent, ast.Constant) \
                    and type(exponent.value) is int and 2 <= exponent.value <= 16:
                return ast.Call(ast.Name("_integer_power", ast.Load()), [self.visit(node.left), exponent], [])
            return self.generic_visit(node)

        def visit_Constant(self, node):
            if type(node.value) is not int:
                return node
            try:
                return ast.copy_location(ast.Constant(float(node.value)), node)
            except OverflowError:  # its own message must not format the integer as a float either
                digits = int(node.value.bit_length() * 0.30102999566398120) + 1
                raise ValueError(f"the integer of about {digits} digits in the level-set expression is too large for a "
                                 "float (at most about 1.8e308): write a smaller number") from None

    return IntegerPowers()


def _expression_function(text):
    """A vectorized f(x) for the expression ``text`` in x, y, z; ValueError for anything not allowed."""
    import ast

    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"a level-set expression must be a non-empty string in x, y, z, got {text!r}")
    if len(text) > _EXPRESSION_MAX_LENGTH:
        raise ValueError(f"the level-set expression is longer than {_EXPRESSION_MAX_LENGTH} characters; use a Python file")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as exc:
        raise ValueError(
            f"cannot parse the level-set expression {text!r}: {exc.msg}; write it in Python syntax, "
            "e.g. 'x**2 + y**2 + z**2 - 1'"
        ) from None
    except (RecursionError, MemoryError):
        raise ValueError("the level-set expression is nested too deeply to be parsed; write it in a Python file "
                         "(FunctionLevelSet.from_file)") from None
    called = {id(node.func) for node in ast.walk(tree) if isinstance(node, ast.Call)}
    operators = (ast.Add, ast.Sub, ast.Mult, ast.Div, ast.Pow, ast.USub, ast.UAdd)
    variables = {"x", "y", "z"} | set(_EXPRESSION_CONSTANTS)
    for node in ast.walk(tree):
        if isinstance(node, (ast.Expression, ast.Load) + operators):
            continue
        if isinstance(node, ast.BitXor):
            raise ValueError(f"the level-set expression {text!r} uses ^, which is not a power in Python: write ** (x**2)")
        if isinstance(node, (ast.BinOp, ast.UnaryOp)):
            continue  # the operator itself is checked as its own node
        if isinstance(node, ast.Constant) and type(node.value) in (int, float):
            continue
        if isinstance(node, ast.Call):
            if not isinstance(node.func, ast.Name) or node.func.id not in _EXPRESSION_FUNCTIONS or node.keywords:
                raise ValueError(
                    f"the level-set expression {text!r} calls {ast.unparse(node)!r}, which is not allowed; "
                    f"the functions are {', '.join(_EXPRESSION_FUNCTIONS)} with positional arguments"
                )
            arity = _EXPRESSION_ARITY[node.func.id]
            if len(node.args) != arity or any(isinstance(a, ast.Starred) for a in node.args):
                raise ValueError(
                    f"the level-set expression {text!r} calls {node.func.id} with {len(node.args)} argument(s) in "
                    f"{ast.unparse(node)!r}; {node.func.id} takes {arity}"
                )
            continue
        if isinstance(node, ast.Name):
            if node.id in _EXPRESSION_FUNCTIONS and id(node) not in called:
                raise ValueError(f"the level-set expression {text!r} uses the function {node.id} without calling it; "
                                 f"write {node.id}(...)")
            if node.id in variables or node.id in _EXPRESSION_FUNCTIONS:
                continue
            raise ValueError(
                f"the level-set expression {text!r} uses the unknown name {node.id!r}; it may use x, y, z, "
                f"pi, e and the functions {', '.join(_EXPRESSION_FUNCTIONS)}"
            )
        raise ValueError(
            f"the level-set expression {text!r} contains {ast.unparse(node) or type(node).__name__!r} ({type(node).__name__}), "
            "which is not allowed: use numbers, x, y, z, pi, e, + - * / ** and the listed numpy functions"
        )
    try:
        tree = ast.fix_missing_locations(_integer_powers_transformer().visit(tree))
        code = compile(tree, "<level-set expression>", "eval")
    except (RecursionError, MemoryError):
        raise ValueError("the level-set expression is nested too deeply to be compiled; write it in a Python file "
                         "(FunctionLevelSet.from_file)") from None

    def expression(x):
        from .intervals import Interval

        if not isinstance(x, Interval):  # intervals: the band search's enclosures (cutfem.geometry.intervals)
            x = np.asarray(x, dtype=float)
        names = {"__builtins__": {}, **_EXPRESSION_FUNCTIONS, **_EXPRESSION_CONSTANTS, "_integer_power": _integer_power,
                 "x": x[..., 0], "y": x[..., 1], "z": x[..., 2]}
        with np.errstate(all="ignore"):  # NaN/inf values are reported by the callers, with the points
            try:
                out = eval(code, names)  # noqa: S307 - the tree was checked above
            except ArithmeticError as exc:  # constants alone: '1/0', '10.0**400' (arrays give inf or NaN)
                raise ValueError(f"the level-set expression {text!r} cannot be evaluated: {exc} in its constants") from None
        if isinstance(x, Interval):
            return out
        if np.iscomplexobj(out):  # '(-8)**(1/3)': Python's power of a negative number is complex
            raise ValueError(f"the level-set expression {text!r} gives complex values (a negative number to a fractional "
                             "power?); a level set is real: write cbrt(-8) or -(8**(1/3))")
        return np.broadcast_to(np.asarray(out, dtype=float), x.shape[:-1]).copy()

    return expression


#: index pairs (i, j), i < j, of the off-diagonal Hessian entries
_PAIRS = np.array([[0, 1], [0, 2], [1, 2]])
#: offsets (in units of h) of the 19 points of the difference Hessian from values: 0, +2e_i, -2e_i,
#: then for each pair (i, j) of _PAIRS the four points +e_i+e_j, +e_i-e_j, -e_i+e_j, -e_i-e_j
_HESSIAN_STENCIL = np.concatenate([
    np.zeros((1, 3)), 2.0 * np.eye(3), -2.0 * np.eye(3),
    np.array([s * np.eye(3)[i] + t * np.eye(3)[j] for i, j in _PAIRS for s, t in ((1, 1), (1, -1), (-1, 1), (-1, -1))]),
])

# ----------------------------------------------------------------------------------------------
# base class
# ----------------------------------------------------------------------------------------------
class LevelSet:
    """A level-set function phi: R^3 -> R whose zero set is a closed surface S.

    Subclasses implement :meth:`value`, :meth:`gradient` and :meth:`hessian`; everything else is
    derived here: the normal and mean curvature of docs/math.md §1 at a point, the closest-point map
    (Newton's method on the closest-point system, :meth:`closest_point`) and the exact fields at
    the closest point.  Subclasses with closed forms (Sphere, Torus, Ellipsoid) override the latter.

    Attributes
    ----------
    lipschitz : float or None
        A global bound L >= sup |grad phi| (1.0 for a true signed distance), or None when no bound
        is known.  The cut uses |phi(x)| > L * diam(T) to skip a background cell T far from the
        surface, so a value given here must really be an upper bound.
    is_distance : bool
        True when phi is the signed distance to S (|grad phi| = 1, Lap phi = k1 + k2 on S).
    area, volume : float or None
        Exact area of S and volume enclosed by S when known.
    newton_steps : int
        Most Newton steps of the general :meth:`closest_point` (12; points near S need 2 to 5).
    """

    newton_steps: int = 12
    lipschitz: float | None = None
    is_distance: bool = False
    area: float | None = None
    volume: float | None = None

    # -- to be provided by subclasses ---------------------------------------------------------
    def value(self, x) -> np.ndarray:
        """phi(x) for points x of shape (..., 3); returns shape (...)."""
        raise NotImplementedError(f"{type(self).__name__} must implement value(x)")

    def gradient(self, x) -> np.ndarray:
        """grad phi(x) for points x of shape (..., 3); returns shape (..., 3)."""
        raise NotImplementedError(f"{type(self).__name__} must implement gradient(x)")

    def hessian(self, x) -> np.ndarray:
        """Hess phi(x) (symmetric) for points x of shape (..., 3); returns shape (..., 3, 3)."""
        raise NotImplementedError(f"{type(self).__name__} must implement hessian(x)")

    def _value_gradient_hessian(self, x):
        """(phi, grad phi, Hess phi) at points x (n, 3): what each Newton step of
        :meth:`closest_point` needs (subclasses may get them from one evaluation)."""
        return self.value(x), self.gradient(x), self.hessian(x)

    def closest_point(self, x) -> np.ndarray:
        """Closest point p(x) on S for points x of shape (..., 3) near S; returns shape (..., 3).

        The general projection, for any smooth level set with :meth:`value`, :meth:`gradient` and
        :meth:`hessian` (subclasses with a closed form override it).  p is a solution of the
        closest-point system in the unknowns (p, mu) in R^3 x R,

            F(p, mu) = (p - x + mu grad phi(p),  phi(p)) = 0,

        (p on S, x - p parallel to grad phi(p)), solved by Newton's method with the 4 x 4 Jacobian

            [[I + mu Hess phi(p), grad phi(p)], [grad phi(p)^T, 0]],

        vectorized over all points (one batched 4 x 4 solve per step, only for the points not yet
        converged).  Start: the first-order projection p0 = x - phi(x) grad phi(x) / |grad phi(x)|^2
        and mu0 = phi(x) / |grad phi(x)|^2, which is within O(dist^2) of the foot point, so Newton
        converges quadratically for points closer to S than a fraction of its smallest curvature
        radius (the quadrature points of a cut surface are O(h^2) away).

        A point is converged when, with L = max(1, |x|_inf) and g = grad phi(p),

            |phi(p)| <= 1e-12 |g| L       (phi vanishes to 1e-12 relative to its scale |g| L), and
            |p - x + mu g| <= 1e-12 L + 1e-9 |x - p|   (x - p parallel to g to the accuracy of a
                                                         difference gradient, about 1e-10),

        and p is then checked to be a local minimizer of |x - p| on S: I + mu Hess phi(p) must be
        positive definite on the tangent plane (x lies before the first focal point).  At most
        :attr:`newton_steps` steps; points that do not converge, or reach a critical point of the
        distance that is not a minimum, raise ValueError naming their count, the first one, and the
        fix (such points are too far from S; evaluate the exact fields only near the surface).
        Where the foot point is not unique (the medial set) the one Newton reaches is returned.
        """
        x = _as_points(x)
        y = x.reshape(-1, 3)
        if len(y) == 0:
            return x.copy()
        p = np.empty_like(y)
        bad = np.zeros(len(y), dtype=bool)
        saddle = np.zeros(len(y), dtype=bool)
        singular = np.zeros(len(y), dtype=bool)
        for start in range(0, len(y), NEWTON_CHUNK):  # chunks: the stencils' temporaries stay in cache
            part = slice(start, start + NEWTON_CHUNK)
            p[part], bad[part], saddle[part], singular[part] = self._newton(y[part])
        _raise_if_singular(singular, y, "the closest-point projection", "where grad phi = 0")
        if bad.any():
            first = y[bad][0]
            raise ValueError(
                f"the closest-point projection of {type(self).__name__} did not converge in "
                f"{self.newton_steps} Newton steps for {int(bad.sum())} of {len(y)} point(s) "
                f"(first: {first}, phi there {float(self.value(first))!r}); it is meant for points "
                "near the surface (closer than its smallest curvature radius): evaluate the exact "
                "fields only near S, or check that phi is smooth and has a nonzero gradient on S"
            )
        if saddle.any():
            first = y[saddle][0]
            raise ValueError(
                f"the closest-point projection of {type(self).__name__} reached a point of S that is "
                f"not nearest for {int(saddle.sum())} of {len(y)} point(s) (first: {first}): these "
                "points lie beyond a focal point of S (too far from the surface for its curvature); "
                "evaluate the exact fields only near S"
            )
        return p.reshape(x.shape)

    def _newton(self, y):
        """Newton's method of :meth:`closest_point` for the points y (n, 3): (p (n, 3), failed (n,),
        saddle (n,), singular (n,)), failed where it did not converge or the step was not finite,
        saddle where the point reached is not a local minimizer of the distance, singular where
        grad phi(y) = 0 (no start)."""
        scale = np.maximum(1.0, np.max(np.abs(y), axis=-1))
        f = self.value(y)
        g = self.gradient(y)
        gg = np.einsum("ij,ij->i", g, g)
        singular = gg == 0.0
        with np.errstate(divide="ignore", invalid="ignore"):  # the singular points are left out below
            mu = f / gg
            p = y - mu[:, None] * g
        todo = np.flatnonzero(~singular)
        saddle = np.zeros(len(y), dtype=bool)
        failed = np.zeros(len(y), dtype=bool)

        for _ in range(self.newton_steps + 1):
            f, g, hess = self._value_gradient_hessian(p[todo])
            keep = np.empty(len(todo), dtype=bool)
            levelset_kernels.closest_point_newton_step(todo, p, y, mu, scale, np.ascontiguousarray(f, dtype=float),
                                              np.ascontiguousarray(g, dtype=float), np.ascontiguousarray(hess, dtype=float),
                                              saddle, failed, keep)
            todo = todo[keep]
            if len(todo) == 0:
                break
        failed[todo] = True
        return p, failed, saddle, singular

    def bounds(self):
        """Axis-aligned bounding box of S as (lower (3,), upper (3,)), or None when not known."""
        return None

    # -- derived quantities -------------------------------------------------------------------
    def normal(self, x) -> np.ndarray:
        """Unit normal n(x) = grad phi(x) / |grad phi(x)| at x itself, shape (..., 3).

        Outward on S by the sign convention (phi < 0 inside).  ValueError where grad phi = 0.
        """
        x = _as_points(x)
        g = self.gradient(x)
        norm = np.linalg.norm(g, axis=-1)
        _raise_if_singular(norm == 0.0, x, "the normal grad phi/|grad phi|", "where grad phi = 0")
        return g / norm[..., None]

    def mean_curvature(self, x) -> np.ndarray:
        """div(grad phi / |grad phi|) at x itself, shape (...).

        Computed as trace(P Hess phi) / |grad phi| = (trace(Hess) - n^T Hess n) / |grad phi| with
        P = I - n n^T.  On S this is k1 + k2 (2/R on a sphere of radius R); off S it is the
        curvature of the level set of phi through x, which differs from (k1 + k2)(p(x)).
        """
        return self._curvature_and_normal(_as_points(x))[0]

    def _gradient_hessian(self, x):
        """(grad phi, Hess phi) at points x (n, 3) (subclasses may get both from one evaluation)."""
        return self.gradient(x), self.hessian(x)

    def _curvature_and_normal(self, x):
        """(div n, n) at the points x (..., 3) from one gradient and one Hessian evaluation, by
        chunks of :data:`NEWTON_CHUNK` points (the difference stencils of a FunctionLevelSet stay
        in cache)."""
        flat = x.reshape(-1, 3)
        if len(flat) > NEWTON_CHUNK:
            g, hess = np.empty((len(flat), 3)), np.empty((len(flat), 3, 3))
            for start in range(0, len(flat), NEWTON_CHUNK):
                part = slice(start, start + NEWTON_CHUNK)
                g[part], hess[part] = self._gradient_hessian(flat[part])
            g, hess = g.reshape(x.shape), hess.reshape(x.shape + (3,))
        else:
            g, hess = self._gradient_hessian(flat)
            g, hess = g.reshape(x.shape), hess.reshape(x.shape + (3,))
        norm = np.linalg.norm(g, axis=-1)
        _raise_if_singular(norm == 0.0, x, "the mean curvature", "where grad phi = 0")
        n = g / norm[..., None]
        trace = np.trace(hess, axis1=-2, axis2=-1)
        nhn = np.einsum("...i,...ij,...j->...", n, hess, n)
        return (trace - nhn) / norm, n

    def exact_mean_curvature(self, x) -> np.ndarray:
        """(k1 + k2)(p(x)): the exact mean curvature at the closest point, shape (...)."""
        return self.mean_curvature(self.closest_point(x))

    def exact_normal(self, x) -> np.ndarray:
        """n(p(x)): the exact outward unit normal at the closest point, shape (..., 3)."""
        return self.normal(self.closest_point(x))

    def exact_mean_curvature_vector(self, x) -> np.ndarray:
        """H^e(x) = H(p(x)) = (k1 + k2)(p(x)) n(p(x)), shape (..., 3).

        With n = grad phi/|grad phi| and k1 + k2 = trace(P Hess phi)/|grad phi|, P = I - n n^T, at
        the closest point p(x) (docs/math.md §1): valid for any level set, distance or not.
        """
        kappa, n = self._curvature_and_normal(self.closest_point(x))
        return kappa[..., None] * n


# ----------------------------------------------------------------------------------------------
# sphere
# ----------------------------------------------------------------------------------------------
class Sphere(LevelSet):
    """Sphere of radius R about c as its signed distance phi(x) = |x - c| - R.

    With r = |x - c| and u = (x - c)/r:  grad phi = u,  Hess phi = (I - u u^T)/r,
    p(x) = c + R u,  n(p(x)) = u,  k1 + k2 = 2/R,  H^e = (2/R) u.
    Area 4 pi R^2, volume 4/3 pi R^3, lipschitz 1.  Derivatives and p are undefined at x = c
    (ValueError there).

    The radius must lie in :data:`cutfem.geometry.surface.LENGTH_RANGE` (1e-50 to 1e50; ValueError at
    construction otherwise): beyond it the area and volume overflow or underflow.  |x - c| is
    numpy's norm, and ``hypot`` where that norm leaves [1e-150, 1e150] (its squares would overflow
    or lose bits to underflow), so points as far as 1e300 or as close to c as 1e-320 are exact.
    """

    is_distance = True
    lipschitz = 1.0

    def __init__(self, radius: float = 1.0, center=(0.0, 0.0, 0.0)):
        self.radius = check_length("radius", radius, "Sphere")
        self.center = _center(center)

    def __repr__(self) -> str:
        return f"Sphere(radius={self.radius!r}, center={tuple(self.center.tolist())!r})"

    @property
    def area(self) -> float:
        return 4.0 * np.pi * self.radius**2

    @property
    def volume(self) -> float:
        return 4.0 / 3.0 * np.pi * self.radius**3

    def bounds(self):
        """(c - R, c + R) componentwise, each of shape (3,)."""
        return self.center - self.radius, self.center + self.radius

    @staticmethod
    def _length(d):
        """|d| along the last axis: numpy's norm, recomputed with ``hypot`` (no squares) where it is
        outside [1e-150, 1e150], i.e. where the squares overflow or underflow."""
        flat = d.reshape(-1, 3)
        with np.errstate(over="ignore", under="ignore"):  # the points concerned are recomputed below
            r = np.linalg.norm(flat, axis=-1)
        careful = ~((r >= 1e-150) & (r <= 1e150))
        if careful.any():
            r[careful] = np.hypot(np.hypot(flat[careful, 0], flat[careful, 1]), flat[careful, 2])
        return r.reshape(d.shape[:-1])

    def _unit(self, x):
        """(x, r, u) with r = |x - c| and u = (x - c)/r; ValueError at the center."""
        x = _as_points(x)
        d = x - self.center
        r = self._length(d)
        _raise_if_singular(r == 0.0, x, "the direction (x - c)/|x - c|", "at the sphere's center")
        return x, r, d / r[..., None]

    def value(self, x):
        """|x - c| - R, shape (...)."""
        x = _as_points(x)
        return self._length(x - self.center) - self.radius

    def gradient(self, x):
        """(x - c)/|x - c|, shape (..., 3)."""
        return self._unit(x)[2]

    def hessian(self, x):
        """(I - u u^T)/|x - c| with u = (x - c)/|x - c|, shape (..., 3, 3)."""
        _, r, u = self._unit(x)
        return (np.eye(3) - u[..., :, None] * u[..., None, :]) / r[..., None, None]

    def closest_point(self, x):
        """c + R (x - c)/|x - c|, shape (..., 3)."""
        return self.center + self.radius * self._unit(x)[2]

    def exact_normal(self, x):
        """(x - c)/|x - c|, shape (..., 3)."""
        return self._unit(x)[2]

    def exact_mean_curvature(self, x):
        """2/R everywhere except the center, shape (...)."""
        _, r, _ = self._unit(x)
        return np.full(r.shape, 2.0 / self.radius)

    def exact_mean_curvature_vector(self, x):
        """(2/R) (x - c)/|x - c|, shape (..., 3)."""
        return (2.0 / self.radius) * self._unit(x)[2]


# ----------------------------------------------------------------------------------------------
# torus
# ----------------------------------------------------------------------------------------------
class Torus(LevelSet):
    """Ring torus with axis z through c, major radius R, minor radius r (0 < r < R).

    Parametrization: x = c + ((R + r cos p) cos t, (R + r cos p) sin t, r sin p).
    Signed distance: with y = x - c, s = sqrt(y1^2 + y2^2), e_s = (y1, y2, 0)/s,
    w = y - R e_s (vector from the nearest point of the core circle), d = |w|, m = w/d:

        rho = d - r = sqrt(y3^2 + (s - R)^2) - r,
        grad rho = m,
        Hess rho = (I - m m^T)/d - R/(s d) e_t e_t^T,   e_t = (-y2, y1, 0)/s,

    (from D w = I - (R/s) e_t e_t^T), p(x) = c + R e_s + r m, n(p(x)) = m, and with
    cos p = m . e_s = (s - R)/d:

        k1 + k2 = (R + 2 r cos p) / (r (R + r cos p)).

    Area 4 pi^2 R r, volume 2 pi^2 R r^2, lipschitz 1 (rho is the signed distance everywhere).
    Derivatives, p and the exact fields are undefined on the z-axis (s = 0) and on the core
    circle (d = 0): ValueError there; anywhere else, however close, they are returned (s and d by
    ``hypot``, the frame from the bounded ratios y/s, (s - R)/d, y3/d).

    R and r must lie in :data:`cutfem.geometry.surface.LENGTH_RANGE` (1e-50 to 1e50; ValueError at
    construction otherwise): beyond it the area and volume overflow or underflow.
    """

    is_distance = True
    lipschitz = 1.0

    def __init__(self, R: float = 1.0, r: float = 0.5, center=(0.0, 0.0, 0.0)):
        self.R = check_length("R", R, "Torus")
        self.r = check_length("r", r, "Torus")
        if not self.r < self.R:
            raise ValueError(
                f"a ring torus needs r < R, got R={R!r}, r={r!r}; choose a minor radius smaller "
                "than the major radius (r >= R gives a self-intersecting horn/spindle torus)"
            )
        self.center = _center(center)

    def __repr__(self) -> str:
        return f"Torus(R={self.R!r}, r={self.r!r}, center={tuple(self.center.tolist())!r})"

    @property
    def area(self) -> float:
        return 4.0 * np.pi**2 * self.R * self.r

    @property
    def volume(self) -> float:
        return 2.0 * np.pi**2 * self.R * self.r**2

    def bounds(self):
        """c -/+ (R + r, R + r, r), each of shape (3,)."""
        half = np.array([self.R + self.r, self.R + self.r, self.r])
        return self.center - half, self.center + half

    def _frame(self, x):
        """Local quantities (x, s, d, e_s, e_t, m); ValueError on the axis or the core circle."""
        x = _as_points(x)
        y = x - self.center
        s = np.hypot(y[..., 0], y[..., 1])
        _raise_if_singular(s == 0.0, x, "the torus distance's derivatives", "on the torus axis")
        e_s = np.stack([y[..., 0] / s, y[..., 1] / s, np.zeros_like(s)], axis=-1)
        e_t = np.stack([-y[..., 1] / s, y[..., 0] / s, np.zeros_like(s)], axis=-1)
        w = y - self.R * e_s
        d = np.hypot(s - self.R, y[..., 2])  # |w|, without squares that overflow or underflow
        _raise_if_singular(d == 0.0, x, "the torus distance's derivatives", "on the core circle")
        m = w / d[..., None]
        return x, s, d, e_s, e_t, m

    def value(self, x):
        """sqrt(y3^2 + (s - R)^2) - r with y = x - c, s = |(y1, y2)|; shape (...).  One compiled
        pass with libm's ``hypot`` (:func:`cutfem.geometry.levelset_kernels.torus_value`: numpy's bits, a third of
        its time; the band search of the cut evaluates it at millions of points)."""
        y = np.asarray(x, dtype=float)
        if y.ndim == 0 or y.shape[-1] != 3:
            _as_points(x)  # raises with the shape

        pts = np.ascontiguousarray(y.reshape(-1, 3))
        out = np.empty(len(pts))
        if not levelset_kernels.torus_value(pts, self.center, self.R, self.r, out):
            _as_points(x)  # raises naming the points that are not finite
        return out.reshape(y.shape[:-1])

    def gradient(self, x):
        """m = (y - R e_s)/|y - R e_s|, shape (..., 3)."""
        return self._frame(x)[5]

    def hessian(self, x):
        """(I - m m^T)/d - R/(s d) e_t e_t^T, shape (..., 3, 3)."""
        _, s, d, _, e_t, m = self._frame(x)
        mm = m[..., :, None] * m[..., None, :]
        tt = e_t[..., :, None] * e_t[..., None, :]
        return (np.eye(3) - mm) / d[..., None, None] - (self.R / (s * d))[..., None, None] * tt

    def closest_point(self, x):
        """c + R e_s + r m, shape (..., 3)."""
        _, _, _, e_s, _, m = self._frame(x)
        return self.center + self.R * e_s + self.r * m

    def exact_normal(self, x):
        """m = n(p(x)), shape (..., 3)."""
        return self._frame(x)[5]

    def exact_mean_curvature(self, x):
        """(R + 2 r cos p)/(r (R + r cos p)) with cos p = m . e_s; shape (...)."""
        _, _, _, e_s, _, m = self._frame(x)
        cos_p = np.einsum("...i,...i->...", m, e_s)
        return (self.R + 2.0 * self.r * cos_p) / (self.r * (self.R + self.r * cos_p))

    def exact_mean_curvature_vector(self, x):
        """(k1 + k2)(p(x)) m, shape (..., 3).

        In closed form, without the frame vectors: with y = x - c, s = |(y1, y2)| and
        d = |(s - R, y3)|, m = ((1 - R/s) y1, (1 - R/s) y2, y3) / d and cos p = (s - R)/d, so

            H^e(x) = kappa / d * ((1 - R/s) y1, (1 - R/s) y2, y3),
            kappa = (R + 2 r cos p) / (r (R + r cos p)).

        This is evaluated at every quadrature point of the error norms (27 million at spacing
        0.00625), hence the lean form in one compiled pass
        (:func:`cutfem.geometry.levelset_kernels.torus_mean_curvature_vector`: plain square roots, and whether the
        result is finite; 0.16 s there, where numpy's dozen passes took 0.35 s).  Where it is not
        finite (NaN or infinite input, a point on the axis or on the core circle, overflow), the
        careful evaluation (``hypot``, the checks of :meth:`_frame`) gives the value or the error.
        """
        y = np.asarray(x, dtype=float)
        if y.ndim == 0 or y.shape[-1] != 3:
            return self._careful_mean_curvature_vector(x)

        points = np.ascontiguousarray(y.reshape(-1, 3))
        out = np.empty_like(points)
        points = points.view()
        points.flags.writeable = False  # a read-only view whatever the caller's: one compiled signature
        if not levelset_kernels.torus_mean_curvature_vector(points, self.center, self.R, self.r, out):
            return self._careful_mean_curvature_vector(x)
        return out.reshape(y.shape)

    def _careful_mean_curvature_vector(self, x):
        """:meth:`exact_mean_curvature_vector` with ``hypot``, the input and singularity checks, and
        H = kappa (cos p e_s + sin p e_z) from the bounded ratios y/s, (s - R)/d, y3/d, so that a
        point 1e-310 from the axis or 1e-320 from the core circle gets its value (not 0 * inf)."""
        x = _as_points(x)
        y = x - self.center
        s = np.hypot(y[..., 0], y[..., 1])
        _raise_if_singular(s == 0.0, x, "the torus distance's derivatives", "on the torus axis")
        s_minus_R = s - self.R
        d = np.hypot(s_minus_R, y[..., 2])
        _raise_if_singular(d == 0.0, x, "the torus distance's derivatives", "on the core circle")
        cos_p, sin_p = s_minus_R / d, y[..., 2] / d  # m = cos p e_s + sin p e_z, from bounded ratios only
        kappa = (self.R + 2.0 * self.r * cos_p) / (self.r * (self.R + self.r * cos_p))
        out = np.empty_like(y)
        out[..., 2] = kappa * sin_p
        out[..., 0] = kappa * cos_p * (y[..., 0] / s)
        out[..., 1] = kappa * cos_p * (y[..., 1] / s)
        return out


# ----------------------------------------------------------------------------------------------
# ellipsoid
# ----------------------------------------------------------------------------------------------
class Ellipsoid(LevelSet):
    """Ellipsoid with semi-axes (a, b, c) along x, y, z about ``center``.

    phi(x) = sum_i (y_i / a_i)^2 - 1 with y = x - center and (a_1, a_2, a_3) = (a, b, c); this is
    NOT a distance (lipschitz None: |grad phi| = 2 |y_i / a_i^2| grows without bound).

        grad phi = 2 y_i / a_i^2,   Hess phi = diag(2 / a_i^2),
        k1 + k2 = trace(P Hess phi) / |grad phi| evaluated at p(x)   (inherited machinery).

    Closest point: p minimizes |p - y|^2 subject to phi = 0.  The Lagrange condition gives
    p_i = y_i a_i^2 / (a_i^2 + t) with t the largest root of

        F(t) = sum_i (a_i y_i / (a_i^2 + t))^2 - 1 = 0.

    Only components with |y_i| > 1e-150 max(a) take part ("active"; smaller ones are treated as 0,
    which changes p by O(|y_i|)).  Let a_k be the smallest active semi-axis; over the active terms F
    is convex and decreasing on t > -a_k^2.  To avoid cancellation near that pole the unknown is the
    shift s = t + a_k^2 > 0, with a_i^2 + t = (a_i^2 - a_k^2) + s.  Newton starts at
    s0 = max_i (a_i |y_i| - (a_i^2 - a_k^2)) >= a_k |y_k| > 0, where F >= 0 (left of the root, right
    of every pole), then increases monotonically and converges quadratically.  A point is done
    when |ds| <= 16 eps s (relative machine precision in the distance to the pole, hence in every
    p_i) or when |F| <= 8 eps (1 + sum_i q_i^2), q_i = a_i y_i / (a_i^2 + t) (the residual is at
    rounding level: phi(p) = 0 holds to machine precision, no further step is meaningful); at most 200 steps,
    otherwise RuntimeError.  Typical counts: under 10 near the surface, a few tens for points far
    away or next to the medial set.

    If some inactive component j has -a_j^2 above the root, the closest point has t = -a_j^2 and
    p_j = sign(y_j) a_j sqrt(1 - sum_{i != j} (p_i / a_i)^2) (largest such -a_j^2): y lies on (or
    within 1e-150 of) the medial set where the closest point is not unique; the returned one is the
    limit from the side of y (p_j >= 0 when y_j = +0).  The center maps to (0, 0, +c) for a > b > c.

    Area (a >= b >= c after sorting, cos(phi) = c/a, m = a^2 (b^2 - c^2) / (b^2 (a^2 - c^2))):
        A = 2 pi c^2 + 2 pi a b (E(phi, m) sin^2 phi + F(phi, m) cos^2 phi) / sin phi
    with the incomplete elliptic integrals F = ellipkinc, E = ellipeinc (parameter m = k^2);
    A = 4 pi a^2 when a = c.  Volume 4/3 pi a b c.

    Mean curvature (at a point x itself, as the base class defines it): with h_i = 2 / a_i^2 and
    n = grad phi / |grad phi|, trace(P Hess phi) = sum_i h_i (1 - n_i^2) = sum_i h_i sum_{j != i} n_j^2,
    which has no cancellation (trace(Hess) - n^T Hess n lost everything on a flat ellipsoid: 0 for
    2e-10 at the centre of the face of (1, 1, 1e-10)).

    Sizes: each semi-axis must lie in :data:`cutfem.geometry.surface.LENGTH_RANGE` (1e-50 to 1e50) and the
    smallest over the largest must be at least :attr:`min_axis_ratio` (1e-12); ValueError at
    construction otherwise.  Below that ratio arccos(c/a) rounds to pi/2 (from about 1e-16) and the
    area formula gives inf or NaN, and at 1e-200 the squares of the semi-axes underflow.
    """

    is_distance = False
    lipschitz = None
    #: the smallest semi-axis over the largest must be at least this (see the class docstring)
    min_axis_ratio = 1e-12

    def __init__(self, a: float = 1.0, b: float = 0.8, c: float = 0.6, center=(0.0, 0.0, 0.0)):
        self.axes = np.array([check_length(k, v, "Ellipsoid") for k, v in (("a", a), ("b", b), ("c", c))])
        ratio = self.axes.min() / self.axes.max()
        if ratio < self.min_axis_ratio:
            raise ValueError(
                f"Ellipsoid: the semi-axes a = {a:g}, b = {b:g}, c = {c:g} have smallest / largest = {ratio:.3g}, below "
                f"{self.min_axis_ratio:g}: the area (elliptic integrals of arccos(smallest / largest)) and the curvatures "
                "underflow to inf or NaN; use a less flat ellipsoid (or a disc-like surface of another kind)."
            )
        self.center = _center(center)

    def __repr__(self) -> str:
        a, b, c = self.axes.tolist()
        return f"Ellipsoid(a={a!r}, b={b!r}, c={c!r}, center={tuple(self.center.tolist())!r})"

    @property
    def volume(self) -> float:
        return 4.0 / 3.0 * np.pi * float(np.prod(self.axes))

    @property
    def area(self) -> float:
        a, b, c = np.sort(self.axes)[::-1]
        if a == c:
            return 4.0 * np.pi * a**2
        cos_phi = c / a
        sin_phi = np.sqrt((1.0 - cos_phi) * (1.0 + cos_phi))
        phi = np.arccos(cos_phi)
        m = a**2 * (b**2 - c**2) / (b**2 * (a**2 - c**2))
        from scipy.special import ellipeinc, ellipkinc  # only here: scipy.special takes 0.1-0.4 s to import

        elliptic = ellipeinc(phi, m) * sin_phi**2 + ellipkinc(phi, m) * cos_phi**2
        return float(2.0 * np.pi * c**2 + 2.0 * np.pi * a * b * elliptic / sin_phi)

    def bounds(self):
        """center -/+ (a, b, c), each of shape (3,)."""
        return self.center - self.axes, self.center + self.axes

    def value(self, x):
        """sum_i ((x - center)_i / a_i)^2 - 1, shape (...)."""
        x = _as_points(x)
        return np.sum(((x - self.center) / self.axes) ** 2, axis=-1) - 1.0

    def gradient(self, x):
        """2 (x - center)_i / a_i^2, shape (..., 3)."""
        x = _as_points(x)
        return 2.0 * (x - self.center) / self.axes**2

    def hessian(self, x):
        """diag(2 / a_i^2) at every point, shape (..., 3, 3)."""
        x = _as_points(x)
        return np.broadcast_to(np.diag(2.0 / self.axes**2), x.shape[:-1] + (3, 3)).copy()

    def _curvature_and_normal(self, x):
        """(div n, n) at the points x (..., 3): trace(P Hess phi) = sum_i h_i sum_{j != i} n_j^2 with
        h_i = 2 / a_i^2 (see the class docstring), divided by |grad phi|."""
        g = self.gradient(x)
        norm = np.linalg.norm(g, axis=-1)
        _raise_if_singular(norm == 0.0, x, "the mean curvature", "where grad phi = 0")
        n = g / norm[..., None]
        n2 = n * n
        h = 2.0 / self.axes**2
        trace = h[0] * (n2[..., 1] + n2[..., 2]) + h[1] * (n2[..., 0] + n2[..., 2]) + h[2] * (n2[..., 0] + n2[..., 1])
        return trace / norm, n

    def closest_point(self, x):
        """Closest point on the ellipsoid, shape (..., 3): Newton on the Lagrange multiplier.

        See the class docstring for the equation, the start, the stopping rule and the medial set.
        """
        x = _as_points(x)
        shape = x.shape
        y = (x - self.center).reshape(-1, 3)
        n_pts = y.shape[0]
        a = self.axes
        a2 = a**2
        rows = np.arange(n_pts)
        active = np.abs(y) > 1e-150 * a.max()  # (m, 3)
        has_active = active.any(axis=1)

        # smallest active semi-axis k per point and offsets d_i = a_i^2 - a_k^2 (>= 0 if active)
        k = np.argmin(np.where(active, a, np.inf), axis=1)
        d = a2[None, :] - a2[k][:, None]  # (m, 3)
        ay = np.where(active, a * np.abs(y), 0.0)

        s = np.where(active, ay - d, -np.inf).max(axis=1)
        s = np.where(has_active, s, 1.0)
        s = np.maximum(s, ay[rows, k])  # guards rounding: s0 >= a_k |y_k| > 0
        todo = has_active.copy()
        for _ in range(200):
            if not todo.any():
                break
            idx = np.flatnonzero(todo)
            sa = s[idx]
            denom = np.where(active[idx], d[idx] + sa[:, None], 1.0)
            q2 = (ay[idx] / denom) ** 2  # (a_i y_i / (a_i^2 + t))^2, zero if inactive
            f = q2.sum(axis=1) - 1.0
            df = -2.0 * np.sum(q2 / denom, axis=1)
            step = -f / df
            s[idx] = sa + step
            at_rounding_level = np.abs(f) <= 8.0 * _EPS * (1.0 + q2.sum(axis=1))
            todo[idx[(np.abs(step) <= 16.0 * _EPS * sa) | at_rounding_level]] = False
        else:
            if todo.any():
                raise RuntimeError(
                    f"ellipsoid closest-point Newton iteration did not converge for "
                    f"{int(todo.sum())} point(s) (first: {x.reshape(-1, 3)[todo][0]})"
                )
        t = np.where(has_active, s - a2[k], -np.inf)

        # medial-set candidate t = -a_j^2 for an inactive component j, when it exceeds the root
        cand = np.where(~active, -a2, -np.inf)
        j = np.argmax(cand, axis=1)
        use_cand = cand[rows, j] > t

        denom = np.where(use_cand[:, None], a2[None, :] - a2[j][:, None], d + s[:, None])
        denom = np.where(active, denom, 1.0)
        p = np.where(active, y * a2 / denom, 0.0)
        if use_cand.any():
            r = np.flatnonzero(use_cand)
            jj = j[r]
            rest = np.sum((p[r] / a) ** 2, axis=1)
            p[r, jj] = np.copysign(a[jj] * np.sqrt(np.clip(1.0 - rest, 0.0, None)), y[r, jj])
        return (p + self.center).reshape(shape)


# ----------------------------------------------------------------------------------------------
# user function
# ----------------------------------------------------------------------------------------------
class FunctionLevelSet(LevelSet):
    """Level set given by user callables: any smooth phi, a distance or not.

    Everything geometric comes from the base class: the normal n = grad phi/|grad phi|, the mean
    curvature k1 + k2 = trace(P Hess phi)/|grad phi| (P = I - n n^T), the closest point p(x) by
    Newton's method on the closest-point system (:meth:`LevelSet.closest_point`, which satisfies
    phi(p) = 0 to 1e-12 relative to |grad phi| max(1, |x|_inf)), and the exact fields at p(x) of
    docs/math.md §1.  Also built from a text expression (:meth:`from_expression`) or a Python file
    (:meth:`from_file`).

    Parameters
    ----------
    value : callable
        f(x) -> phi, mapping points of shape (..., 3) to shape (...) (vectorized over any leading
        shape: the finite differences call it on arrays of shape (..., k, 3), so write x[..., 0],
        not x[:, 0]).  A wrong output shape, e.g. (n, 1) or a scalar or (3,) for x of shape (n, 3),
        raises ValueError at the first evaluation, naming the expected shape and the likely fix.
    gradient, hessian : callable or None
        grad phi (..., 3) and Hess phi (..., 3, 3), checked likewise.  When missing they are central
        differences, h scaled with the point's size max(1, |x|_inf):
          * gradient: g_j = (f(x + h e_j) - f(x - h e_j)) / (2h),  h = eps^(1/3) max(1, |x|_inf)
            (the truncation error, h^2 times third derivatives, balances the rounding eps |f| / h);
          * Hessian from a given gradient: H_ij = (g_i(x + h e_j) - g_i(x - h e_j)) / (2h),
            h = eps^(1/3) max(1, |x|_inf), then symmetrized;
          * Hessian from values only: H_ij = (f(x+he_i+he_j) - f(x+he_i-he_j) - f(x-he_i+he_j)
            + f(x-he_i-he_j)) / (4h^2), h = eps^(1/4) max(1, |x|_inf).
        ``step`` (a float) overrides the relative factor eps^(1/3) / eps^(1/4) by an absolute h.
        Measured on the tanglecube sum_i (x_i^4 - 5 x_i^2) + 11.8 near its zero set, relative to the
        largest entry: gradient 1e-10, Hessian from the gradient 3e-11, Hessian from values 1e-8;
        the mean curvature vector from values only is then within 1e-7 of the analytic one.  The
        difference gradient is not smooth at the 1e-10 level, so with it x - p is parallel to
        grad phi(p) to about 1e-10 |x - p| (to round-off with an analytic gradient).
    lipschitz : float or None
        A true global bound on |grad phi| (used to skip cells in the cut), or None.
    is_distance : bool
        Whether phi is a signed distance (information only; the projection is the same Newton
        iteration, which starts from the exact foot point x - phi grad phi of a distance).
    area, volume : float or None
        Exact values when the caller knows them.
    bounds : (lower, upper) or six numbers, or None
        A box containing the surface when known (the problems grow it by 0.1 into the background
        box); without it the problems ask for an explicit box.
    name : str or None
        Shown by repr (the expression or file the level set came from).
    """

    def __init__(self, value, gradient=None, hessian=None, lipschitz=None, is_distance=False,
                 area=None, volume=None, bounds=None, step=None, name=None):
        for label, fn in (("value", value), ("gradient", gradient), ("hessian", hessian)):
            if fn is not None and not callable(fn):
                raise ValueError(f"{label} must be a callable f(x) of points (..., 3), got {fn!r}")
        if value is None:
            raise ValueError("value must be a callable f(x) of points (..., 3) returning shape (...)")
        self._value = value
        self._gradient = gradient
        self._hessian = hessian
        self.lipschitz = None if lipschitz is None else positive_number(lipschitz, "lipschitz")
        self.is_distance = bool(is_distance)
        self.area = None if area is None else positive_number(area, "area")
        self.volume = None if volume is None else positive_number(volume, "volume")
        self.step = None if step is None else positive_number(step, "step")
        self.name = name if name is not None else getattr(value, "__name__", "f")
        self._bounds = None if bounds is None else _as_bounds(bounds, "bounds")
        self._source = None  # the path of a surface file (from_file): its errors name the file

    def __repr__(self) -> str:
        return f"FunctionLevelSet({self.name}, is_distance={self.is_distance}, lipschitz={self.lipschitz})"

    @classmethod
    def from_expression(cls, text: str, **kwargs) -> "FunctionLevelSet":
        """The level set phi(x, y, z) written as a text expression, e.g. ``"x**2 + y**2 + z**2 - 1"``.

        The text is parsed (Python syntax) and checked before anything is evaluated: it may use
        the coordinates ``x``, ``y``, ``z``, numbers, the constants ``pi`` and ``e``, the operators
        ``+ - * / **`` and the numpy functions ``sin cos tan arcsin arccos arctan arctan2 sinh cosh
        tanh exp log log2 log10 sqrt cbrt abs hypot minimum maximum``, called with positional
        arguments; any other name, attribute, subscript, keyword, comparison or statement is
        refused with ValueError (``^`` with a hint to write ``**``).  It is evaluated by numpy on
        whole arrays with no builtins in reach.  Derivatives are central differences (see the
        class); ``kwargs`` go to the constructor (``bounds``, ``lipschitz``, ``area``, ...).
        """
        return cls(_expression_function(text), name=repr(str(text)), **kwargs)

    @classmethod
    def from_file(cls, path) -> "FunctionLevelSet":
        """The level set defined by a Python file.

        The file is run (it is the user's own code, with full Python) and must define

        * ``phi(x)``: phi at points x of shape (..., 3), returning shape (...);

        and may define

        * ``grad(x)`` -> (..., 3) and ``hessian(x)`` -> (..., 3, 3): analytic derivatives
          (otherwise central differences, see the class);
        * ``lipschitz``: a true bound on |grad phi| (lets the cut skip cells far from S);
        * ``box``: a box containing the surface, six numbers (x0, y0, z0, x1, y1, z1) or a pair
          (lower, upper); the problems grow it by 0.1 into the background box (``--box`` overrides);
        * ``area``: the exact area of S (adds ``area_error`` to the records).

        Other names (imports, helpers) are ignored.  Example, a sphere written as a polynomial::

            import numpy as np

            def phi(x):
                return np.sum(x**2, axis=-1) - 1.0

            def grad(x):
                return 2.0 * x

            box = (-1, -1, -1, 1, 1, 1)
        """
        import runpy
        from pathlib import Path

        path = Path(path)
        if not path.is_file():
            raise ValueError(f"surface file {str(path)!r} does not exist; give the path of a Python file that defines phi(x)")
        try:
            ns = runpy.run_path(str(path), run_name="cutfem_surface")
        except (Exception, SystemExit) as exc:  # a file that exits must not end the caller's process
            raise ValueError(f"running the surface file {str(path)!r} failed: {type(exc).__name__}: {exc}") from exc
        if not callable(ns.get("phi")):
            raise ValueError(
                f"the surface file {str(path)!r} defines no function phi(x); define phi(x) for points x "
                "of shape (..., 3) returning shape (...), and optionally grad, hessian, lipschitz, box, area"
            )
        box = ns.get("box")
        try:
            levelset = cls(ns["phi"], gradient=ns.get("grad"), hessian=ns.get("hessian"), lipschitz=ns.get("lipschitz"),
                           area=ns.get("area"), bounds=None if box is None else _as_bounds(box, f"box in {path.name}"),
                           name=repr(str(path)))
        except ValueError as exc:  # a bad lipschitz, area or box: say which file defines it
            raise ValueError(f"the surface file {str(path)!r}: {exc} (leave lipschitz out when no true bound on "
                             "|grad phi| is known: every node is then evaluated)") from exc
        levelset._source = str(path)  # its functions' errors name the file (see _call)
        return levelset

    def bounds(self):
        """The box containing the surface given at construction, or None."""
        return self._bounds

    #: the names of the callables in a surface file (:meth:`from_file`)
    _FILE_NAMES = {"value": "phi", "gradient": "grad", "hessian": "hessian"}

    def _call(self, fn, x, tail, name):
        """fn(x) as floats, checked to be real numbers of shape x.shape[:-1] + tail (ValueError naming
        the function, what it returned and the fix).  For a level set from a surface file
        (:meth:`from_file`) the messages name the file and its function (``phi``, ``grad``,
        ``hessian``), and any exception of that function becomes a ValueError naming the exception
        and the line of the file it came from: it is the user's input that failed, and the command
        line reports it as such (exit status 2)."""
        source = getattr(self, "_source", None)  # a subclass may not call this class's __init__
        prefix = "" if source is None else f"the surface file {source!r}: "
        if source is not None:
            name = self._FILE_NAMES.get(name, name)
        try:
            raw = fn(x)
        except IndexError as exc:
            raise ValueError(
                f"{prefix}{name}(x) raised IndexError ({exc}) for x of shape {x.shape}: the coordinates are along "
                "the last axis of x and there may be several leading axes; write x[..., 0], x[..., 1], "
                "x[..., 2] (not x[:, 0] or x[0])"
            ) from exc
        except MemoryError:
            raise
        except Exception as exc:
            if source is None:
                raise
            import traceback

            frames = [f for f in traceback.extract_tb(exc.__traceback__) if f.filename == source]
            where = f" at line {frames[-1].lineno} ({frames[-1].line})" if frames else ""
            raise ValueError(f"{prefix}{name}(x) raised {exc!r}{where} for points x of shape {x.shape}: fix {name} "
                             "(it must accept points x of shape (..., 3))") from exc
        if np.iscomplexobj(raw):  # float() would drop the imaginary part with only a warning
            raise ValueError(f"{prefix}{name}(x) returned complex values; a level set is real: return the real part "
                             "explicitly if that is what is meant")
        kind = raw.dtype if isinstance(raw, np.ndarray) else np.asarray(raw).dtype
        if kind.kind not in "biuf":  # strings, objects (None would become NaN), dates: not numbers
            first = np.asarray(raw).reshape(-1)[:1]
            raise ValueError(f"{prefix}{name}(x) returned values of dtype {kind} ({'e.g. ' + repr(first[0]) if first.size else 'empty'}, "
                             f"shape {np.shape(raw)}) for points x of shape {x.shape}; it must return real numbers "
                             f"(floats) of shape {x.shape[:-1] + tail}")
        out = np.asarray(raw, dtype=float)
        expected = x.shape[:-1] + tail
        if out.shape != expected:
            raise ValueError(prefix + _shape_message(name, out.shape, x.shape, expected))
        return out

    def _h(self, x, power):
        if self.step is not None:
            return np.full(x.shape[:-1], self.step)
        scale = np.maximum(1.0, np.max(np.abs(x), axis=-1))
        return _EPS**power * scale

    def _gradient_hessian(self, x):
        """(grad phi, Hess phi) at points x (n, 3) from :meth:`_value_gradient_hessian`."""
        return self._value_gradient_hessian(x)[1:]

    def _value_gradient_hessian(self, x):
        """(phi, grad phi, Hess phi) at points x (n, 3) with as few calls of the user's callables as
        the given derivatives allow: without derivatives one call of phi on the 25 points of both
        difference stencils per point (:func:`cutfem.geometry.levelset_kernels.difference_stencil`; phi at x is the
        Hessian stencil's centre), with a gradient but no Hessian one call of it at x and its 6
        neighbours; the same numbers as :meth:`value`, :meth:`gradient` and :meth:`hessian`."""

        if self._hessian is not None:
            return self.value(x), self.gradient(x), self.hessian(x)
        x = np.ascontiguousarray(x, dtype=float)
        h1 = np.ascontiguousarray(self._h(x, 1.0 / 3.0))
        if self._gradient is not None:
            offsets = h1[:, None, None] * np.eye(3)
            xs = np.concatenate([x[:, None, :], x[:, None, :] + offsets, x[:, None, :] - offsets], axis=1)
            g = self._call(self._gradient, xs, (3,), "gradient")  # (n, 7, 3)
            hj = (g[:, 1:4, :] - g[:, 4:7, :]) / (2.0 * h1[:, None, None])
            hess = np.swapaxes(hj, -1, -2)
            return self.value(x), g[:, 0], 0.5 * (hess + np.swapaxes(hess, -1, -2))
        h2 = np.ascontiguousarray(self._h(x, 0.25))
        xs = np.empty((len(x), 25, 3))
        levelset_kernels.difference_stencil(x, h1, h2, _HESSIAN_STENCIL, xs)
        f = np.ascontiguousarray(self._call(self._value, xs, (), "value"))
        value, gradient, hessian = np.empty(len(x)), np.empty((len(x), 3)), np.empty((len(x), 3, 3))
        levelset_kernels.difference_derivatives(f, h1, h2, _PAIRS, value, gradient, hessian)
        return value, gradient, hessian

    def value(self, x):
        """phi(x) from the user callable, shape (...); ValueError on a wrong output shape."""
        x = _as_points(x)
        return self._call(self._value, x, (), "value")

    def gradient(self, x):
        """grad phi, shape (..., 3): the user callable, else central differences of value."""
        x = _as_points(x)
        if self._gradient is not None:
            return self._call(self._gradient, x, (3,), "gradient")
        h = self._h(x, 1.0 / 3.0)[..., None, None]
        offsets = h * np.eye(3)  # (..., 3, 3): row j is h e_j
        xs = np.concatenate([x[..., None, :] + offsets, x[..., None, :] - offsets], axis=-2)
        f = self._call(self._value, xs, (), "value")
        return (f[..., :3] - f[..., 3:]) / (2.0 * h[..., 0])

    def hessian(self, x):
        """Hess phi, shape (..., 3, 3): the user callable, else central differences (see class)."""
        x = _as_points(x)
        if self._hessian is not None:
            return self._call(self._hessian, x, (3, 3), "hessian")
        if self._gradient is not None:
            h = self._h(x, 1.0 / 3.0)[..., None, None]
            offsets = h * np.eye(3)
            xs = np.concatenate([x[..., None, :] + offsets, x[..., None, :] - offsets], axis=-2)
            g = self._call(self._gradient, xs, (3,), "gradient")  # (..., 6, 3)
            # column j of the Hessian = (g(x + h e_j) - g(x - h e_j)) / (2h)
            hj = (g[..., :3, :] - g[..., 3:, :]) / (2.0 * h)  # (..., j, i)
            hess = np.swapaxes(hj, -1, -2)
            return 0.5 * (hess + np.swapaxes(hess, -1, -2))
        # the 19 distinct points of the stencil: x, x +- 2h e_i (diagonal, where the four points
        # x +- h e_i +- h e_i are x + 2h e_i, x, x, x - 2h e_i) and x + s h e_i + t h e_j, i < j
        h = self._h(x, 0.25)
        f = self._call(self._value, x[..., None, :] + h[..., None, None] * _HESSIAN_STENCIL, (), "value")
        diag = (f[..., 1:4] - 2.0 * f[..., :1] + f[..., 4:7]) / (4.0 * h[..., None] ** 2)
        pairs = f[..., 7:].reshape(f.shape[:-1] + (3, 4))  # (..., pair, sign pattern ++ +- -+ --)
        off = (pairs[..., 0] - pairs[..., 1] - pairs[..., 2] + pairs[..., 3]) / (4.0 * h[..., None] ** 2)
        hess = np.zeros(x.shape[:-1] + (3, 3))
        hess[..., [0, 1, 2], [0, 1, 2]] = diag
        hess[..., _PAIRS[:, 0], _PAIRS[:, 1]] = off
        hess[..., _PAIRS[:, 1], _PAIRS[:, 0]] = off
        return hess


# ----------------------------------------------------------------------------------------------
# triangle mesh
# ----------------------------------------------------------------------------------------------
def _surface_arrays(surface):
    """(points (N, 3) float64, triangles (M, 3) int64) from a PolyData or a points/triangles object,
    without the points that no triangle uses."""
    try:
        import pyvista as pv
    except ImportError:  # pragma: no cover - pyvista is a hard dependency
        pv = None
    if pv is not None and isinstance(surface, pv.PolyData):
        if surface.n_cells == 0 or not surface.is_all_triangles:
            raise ValueError(
                "surface must be a closed triangle mesh; this PolyData has non-triangle cells "
                "(or none): call surface.triangulate() first"
            )
        tris = np.asarray(surface.faces, dtype=np.int64).reshape(-1, 4)[:, 1:]
        pts = np.asarray(surface.points, dtype=float)
    elif hasattr(surface, "points") and hasattr(surface, "triangles"):
        pts = np.asarray(surface.points, dtype=float)
        tris = np.asarray(surface.triangles)
        if not np.issubdtype(tris.dtype, np.integer):
            raise ValueError(f"surface.triangles must be integer indices, got dtype {tris.dtype}")
        tris = tris.astype(np.int64)
    else:
        raise ValueError(
            f"surface must be a pyvista.PolyData or have .points (N, 3) and .triangles (M, 3), "
            f"got {type(surface).__name__}"
        )
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise ValueError(f"surface points must be finite with shape (N, 3), got shape {pts.shape}")
    if tris.ndim != 2 or tris.shape[1] != 3 or len(tris) == 0:
        raise ValueError(f"surface triangles must have shape (M, 3), M > 0; got {tris.shape}")
    if tris.min() < 0 or tris.max() >= len(pts):
        raise ValueError(
            f"surface triangles index points outside 0..{len(pts) - 1} "
            f"(range {tris.min()}..{tris.max()})"
        )
    used = unique_keys(tris)
    return pts[used], np.searchsorted(used, tris)


class SignedDistance(LevelSet):
    """Signed distance to a closed triangle mesh (negative inside).

    The mesh is validated and oriented by :class:`cutfem.geometry.surface.SurfaceMesh`, the one validation
    of meshed surfaces (a SurfaceMesh is taken as it is; a pyvista PolyData or an object with
    ``points`` and ``triangles`` is built into one, after dropping the points no triangle uses):
    finite points, no degenerate or duplicate triangles, closed, edge- and vertex-manifold,
    consistently oriented, connected components neither intersecting nor nested, and **each
    component oriented outward on its own** (a set of disjoint spheres, some of them given inside
    out, has every sphere's inside negative).  Each failure is a ValueError naming the offenders
    and the fix.

    Values come from one compiled nearest-point pass over a bounding-volume hierarchy of the
    triangles built once (:meth:`cutfem.geometry.surface.SurfaceMesh.signed_distance`, :mod:`cutfem.geometry.closest`):
    |phi(x)| is the exact distance to the nearest point of the triangles, and the sign is that of
    (x - p) . N with N the angle-weighted pseudo-normal of the face, edge or vertex the nearest
    point p lies on (exact for a closed, outward oriented manifold mesh); points outside the mesh's
    bounding box are outside.  Points farther than 1e150 from the mesh are refused (ValueError).

    gradient: central differences of value with h = 1e-6 * (mesh bounding-box diagonal); this is
    the exact gradient wherever the distance is smooth over the stencil (away from the medial set
    and from points within h of a mesh edge or vertex).
    closest_point: the nearest point of the triangles, computed directly
    (:meth:`cutfem.geometry.surface.SurfaceMesh.closest_points`), so it lies on the mesh and
    |x - p| = |phi(x)| everywhere, also at the centre of a sphere mesh (where the difference
    gradient is 0) and far away; where the nearest point is not unique one of them is returned.
    The Hessian (and hence curvature) of a polyhedral distance carries no curvature information:
    hessian raises NotImplementedError.  ``area`` and ``volume`` are those of the polyhedron,
    lipschitz 1, is_distance True, bounds the points' bounding box; ``mesh`` is the SurfaceMesh.
    """

    is_distance = True
    lipschitz = 1.0

    def __init__(self, surface):
        mesh = surface if isinstance(surface, SurfaceMesh) else SurfaceMesh(*_surface_arrays(surface))
        pts, tris = np.asarray(mesh.points), np.asarray(mesh.triangles)
        self.mesh = mesh
        self.points = pts
        self.triangles = tris
        self.area = mesh.area
        self.volume = mesh.enclosed_volume
        self._diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))

    def __repr__(self) -> str:
        return f"SignedDistance(<{len(self.points)} points, {len(self.triangles)} triangles>)"

    def bounds(self):
        """Bounding box of the mesh points, (lower (3,), upper (3,))."""
        return self.points.min(axis=0), self.points.max(axis=0)

    def value(self, x):
        """Signed distance to the mesh (negative inside), shape (...)."""
        x = _as_points(x)
        flat = x.reshape(-1, 3)
        if flat.shape[0] == 0:
            return np.zeros(x.shape[:-1])
        return self.mesh.signed_distance(flat)[0].reshape(x.shape[:-1])

    def gradient(self, x):
        """Central differences of value, h = 1e-6 * bounding-box diagonal; shape (..., 3)."""
        x = _as_points(x)
        h = 1e-6 * self._diag
        offsets = h * np.eye(3)
        xs = np.concatenate([x[..., None, :] + offsets, x[..., None, :] - offsets], axis=-2)
        f = self.value(xs)
        return (f[..., :3] - f[..., 3:]) / (2.0 * h)

    def hessian(self, x):
        """Not available: a polyhedral distance has no meaningful Hessian (curvature)."""
        raise NotImplementedError(
            "SignedDistance is the distance to a flat-faced mesh: its Hessian carries no "
            "curvature of the underlying smooth surface; use an analytic LevelSet for curvatures"
        )

    def closest_point(self, x):
        """The nearest point of the mesh's triangles, shape (..., 3)
        (:meth:`cutfem.geometry.surface.SurfaceMesh.closest_points`)."""
        x = _as_points(x)
        return self.mesh.closest_points(x.reshape(-1, 3))[0].reshape(x.shape)


# ----------------------------------------------------------------------------------------------
# nodal interpolation
# ----------------------------------------------------------------------------------------------
def interpolate(levelset: LevelSet, points) -> np.ndarray:
    """Nodal values phi(x_i) of a level set at points (n, 3); returns (n,) float64.

    This is the nodal interpolant rho_h of docs/math.md §2 given by its nodal values.  ValueError
    if the points are not (n, 3) or if any value is NaN or infinite (the count and the first bad
    point are named; the level set is probably evaluated outside its domain of definition).
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {pts.shape}")
    values = np.asarray(levelset.value(pts), dtype=float)
    if values.shape != (pts.shape[0],):
        raise ValueError(
            f"levelset.value returned shape {values.shape} for {pts.shape[0]} points; expected "
            f"({pts.shape[0]},)"
        )
    bad = ~np.isfinite(values)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"level set is NaN or infinite at {int(bad.sum())} of {len(values)} point(s) "
            f"(first: point {i} = {pts[i]}, value {values[i]}); check the level set's domain "
            "(e.g. a sqrt/log of a negative number) or that the mesh lies where it is defined"
        )
    return values
