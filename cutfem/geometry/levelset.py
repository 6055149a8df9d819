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

Here: :class:`LevelSet`, the base class (normal, curvature and exact-field machinery on top of
value/gradient/hessian); :class:`FunctionLevelSet`, user callables, a text expression in x, y, z
(parsed by :mod:`cutfem.geometry.expressions`) or a Python file, with derivatives by central
differences when not given; and :func:`interpolate` (nodal values of a level set, with a
finiteness check).  The named surfaces with closed forms (Sphere, Torus, Ellipsoid) are in
:mod:`cutfem.geometry.shapes`, the signed distance to a triangle mesh in
:mod:`cutfem.geometry.signed_distance`.
"""

from __future__ import annotations

import numpy as np

from .expressions import expression_function
from .surface import positive_number
from . import levelset_kernels

__all__ = ["LevelSet", "FunctionLevelSet", "interpolate"]

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
        return cls(expression_function(text), name=repr(str(text)), **kwargs)

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
