"""Level-set descriptions of closed surfaces and their exact geometric data.

A closed surface S in R^3 is the zero set of a function phi: R^3 -> R with the sign convention of
SPEC section 1:

* phi < 0 inside, phi > 0 outside;
* outward unit normal n = grad phi / |grad phi|;
* mean curvature (sum of the principal curvatures) k1 + k2 = div n = trace(P Hess phi) / |grad phi|,
  P = I - n n^T, so that a sphere of radius R has k1 + k2 = 2/R;
* mean curvature vector H = (k1 + k2) n (points outward on a sphere);
* closest-point map p(x) in S; the exact fields used to measure errors are extended constantly
  along normals: H^e(x) = H(p(x)), n^e(x) = n(p(x)).

Every point argument is an array of shape (..., 3); scalar results have shape (...), vector results
(..., 3) and matrix results (..., 3, 3).  Lengths are in the units of the coordinates.

Classes
-------
LevelSet          base class (normal, curvature and exact-field machinery on top of value/gradient/hessian)
Sphere            signed distance |x - c| - R
Torus             signed distance to a ring torus with axis z
Ellipsoid         the quadratic (x/a)^2 + (y/b)^2 + (z/c)^2 - 1 (not a distance)
FunctionLevelSet  a user callable, derivatives by central differences when not given
SignedDistance    signed distance to a closed triangle mesh, evaluated by VTK

and the function :func:`interpolate` (nodal values of a level set, with a finiteness check).
"""

from __future__ import annotations

import numpy as np
from scipy.special import ellipeinc, ellipkinc

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


def _positive(value, name: str) -> float:
    """Return ``value`` as a float, ValueError unless it is finite and > 0."""
    v = float(value)
    if not np.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name} must be a finite positive number, got {value!r}")
    return v


def _center(center) -> np.ndarray:
    """Return ``center`` as a float array of shape (3,), ValueError otherwise."""
    c = np.asarray(center, dtype=float)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise ValueError(f"center must be 3 finite coordinates, got {center!r}")
    return c


# ----------------------------------------------------------------------------------------------
# base class
# ----------------------------------------------------------------------------------------------
class LevelSet:
    """A level-set function phi: R^3 -> R whose zero set is a closed surface S.

    Subclasses implement :meth:`value`, :meth:`gradient` and :meth:`hessian` (and, when available,
    :meth:`closest_point`); everything else is derived here.

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
    """

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

    def closest_point(self, x) -> np.ndarray:
        """Closest point p(x) on S for points x of shape (..., 3); returns shape (..., 3)."""
        raise NotImplementedError(
            f"closest_point is not available for {type(self).__name__}: the closest-point map of a "
            "general level set needs a surface-specific projection; use Sphere, Torus, Ellipsoid, "
            "SignedDistance, or a FunctionLevelSet with is_distance=True (p = x - phi grad phi)"
        )

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
        x = _as_points(x)
        g = self.gradient(x)
        hess = self.hessian(x)
        norm = np.linalg.norm(g, axis=-1)
        _raise_if_singular(norm == 0.0, x, "the mean curvature", "where grad phi = 0")
        n = g / norm[..., None]
        trace = np.trace(hess, axis1=-2, axis2=-1)
        nhn = np.einsum("...i,...ij,...j->...", n, hess, n)
        return (trace - nhn) / norm

    def exact_mean_curvature(self, x) -> np.ndarray:
        """(k1 + k2)(p(x)): the exact mean curvature at the closest point, shape (...)."""
        return self.mean_curvature(self.closest_point(x))

    def exact_normal(self, x) -> np.ndarray:
        """n(p(x)): the exact outward unit normal at the closest point, shape (..., 3)."""
        return self.normal(self.closest_point(x))

    def exact_mean_curvature_vector(self, x) -> np.ndarray:
        """H^e(x) = H(p(x)) = (k1 + k2)(p(x)) n(p(x)), shape (..., 3)."""
        p = self.closest_point(x)
        return self.mean_curvature(p)[..., None] * self.normal(p)


# ----------------------------------------------------------------------------------------------
# sphere
# ----------------------------------------------------------------------------------------------
class Sphere(LevelSet):
    """Sphere of radius R about c as its signed distance phi(x) = |x - c| - R.

    With r = |x - c| and u = (x - c)/r:  grad phi = u,  Hess phi = (I - u u^T)/r,
    p(x) = c + R u,  n(p(x)) = u,  k1 + k2 = 2/R,  H^e = (2/R) u.
    Area 4 pi R^2, volume 4/3 pi R^3, lipschitz 1.  Derivatives and p are undefined at x = c
    (ValueError there).
    """

    is_distance = True
    lipschitz = 1.0

    def __init__(self, radius: float = 1.0, center=(0.0, 0.0, 0.0)):
        self.radius = _positive(radius, "radius")
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

    def _unit(self, x):
        """(x, r, u) with r = |x - c| and u = (x - c)/r; ValueError at the center."""
        x = _as_points(x)
        d = x - self.center
        r = np.linalg.norm(d, axis=-1)
        _raise_if_singular(r == 0.0, x, "the direction (x - c)/|x - c|", "at the sphere's center")
        return x, r, d / r[..., None]

    def value(self, x):
        """|x - c| - R, shape (...)."""
        x = _as_points(x)
        return np.linalg.norm(x - self.center, axis=-1) - self.radius

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
    circle (d = 0): ValueError there.
    """

    is_distance = True
    lipschitz = 1.0

    def __init__(self, R: float = 1.0, r: float = 0.5, center=(0.0, 0.0, 0.0)):
        self.R = _positive(R, "R (major radius)")
        self.r = _positive(r, "r (minor radius)")
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
        d = np.linalg.norm(w, axis=-1)
        _raise_if_singular(d == 0.0, x, "the torus distance's derivatives", "on the core circle")
        m = w / d[..., None]
        return x, s, d, e_s, e_t, m

    def value(self, x):
        """sqrt(y3^2 + (s - R)^2) - r with y = x - c, s = |(y1, y2)|; shape (...)."""
        x = _as_points(x)
        y = x - self.center
        s = np.hypot(y[..., 0], y[..., 1])
        return np.hypot(y[..., 2], s - self.R) - self.r

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

        This is evaluated at every quadrature point of the error norms, hence the lean form: plain
        square roots and one test that the result is finite.  Where it is not (NaN or infinite
        input, a point on the axis or on the core circle, overflow), the careful evaluation
        (``hypot``, the checks of :meth:`_frame`) gives the value or the error.
        """
        y = np.asarray(x, dtype=float)
        if y.ndim == 0 or y.shape[-1] != 3:
            return self._careful_mean_curvature_vector(x)
        if self.center.any():
            y = y - self.center
        y0, y1, y2 = y[..., 0], y[..., 1], y[..., 2]
        with np.errstate(all="ignore"):
            s = np.sqrt(y0 * y0 + y1 * y1)
            s_minus_R = s - self.R
            d = np.sqrt(s_minus_R * s_minus_R + y2 * y2)
            cos_p = s_minus_R / d
            scale = (self.R + 2.0 * self.r * cos_p) / (self.r * d * (self.R + self.r * cos_p))
            out = np.empty_like(y)
            np.multiply(scale, y2, out=out[..., 2])
            scale *= s_minus_R / s
            np.multiply(scale, y0, out=out[..., 0])
            np.multiply(scale, y1, out=out[..., 1])
        if not np.isfinite(out).all():
            return self._careful_mean_curvature_vector(x)
        return out

    def _careful_mean_curvature_vector(self, x):
        """:meth:`exact_mean_curvature_vector` with ``hypot`` and the input and singularity checks."""
        x = _as_points(x)
        y = x - self.center
        s = np.hypot(y[..., 0], y[..., 1])
        _raise_if_singular(s == 0.0, x, "the torus distance's derivatives", "on the torus axis")
        s_minus_R = s - self.R
        d = np.hypot(s_minus_R, y[..., 2])
        _raise_if_singular(d == 0.0, x, "the torus distance's derivatives", "on the core circle")
        cos_p = s_minus_R / d
        scale = (self.R + 2.0 * self.r * cos_p) / (self.r * d * (self.R + self.r * cos_p))
        out = np.empty_like(y)
        out[..., 2] = scale * y[..., 2]
        scale *= s_minus_R / s
        out[..., 0] = scale * y[..., 0]
        out[..., 1] = scale * y[..., 1]
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
    """

    is_distance = False
    lipschitz = None

    def __init__(self, a: float = 1.0, b: float = 0.8, c: float = 0.6, center=(0.0, 0.0, 0.0)):
        self.axes = np.array([_positive(a, "a"), _positive(b, "b"), _positive(c, "c")])
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
    """Level set given by user callables.

    Parameters
    ----------
    value : callable
        f(x) -> phi, mapping points of shape (..., 3) to shape (...) (vectorized over any leading
        shape: the finite differences call it on arrays of shape (..., k, 3)).
    gradient, hessian : callable or None
        grad phi (..., 3) and Hess phi (..., 3, 3).  When missing they are central differences:
          * gradient: g_j = (f(x + h e_j) - f(x - h e_j)) / (2h),  h = eps^(1/3) max(1, |x|_inf);
          * Hessian from a given gradient: H_ij = (g_i(x + h e_j) - g_i(x - h e_j)) / (2h),
            h = eps^(1/3) max(1, |x|_inf), then symmetrized;
          * Hessian from values only: H_ij = (f(x+he_i+he_j) - f(x+he_i-he_j) - f(x-he_i+he_j)
            + f(x-he_i-he_j)) / (4h^2), h = eps^(1/4) max(1, |x|_inf).
        ``step`` (a float) overrides the relative factor eps^(1/3) / eps^(1/4) by an absolute h.
        Expected accuracy ~1e-10 (gradient) and ~1e-7 (Hessian) relative to the derivative scale.
    lipschitz : float or None
        A true global bound on |grad phi| (used to skip cells in the cut), or None.
    is_distance : bool
        Whether phi is a signed distance; then closest_point(x) = x - phi(x) grad phi(x).
    area, volume : float or None
        Exact values when the caller knows them.
    bounds : (lower, upper) or None
        Bounding box of the surface when known.
    """

    def __init__(self, value, gradient=None, hessian=None, lipschitz=None, is_distance=False,
                 area=None, volume=None, bounds=None, step=None):
        for name, fn in (("value", value), ("gradient", gradient), ("hessian", hessian)):
            if fn is not None and not callable(fn):
                raise ValueError(f"{name} must be a callable f(x) of points (..., 3), got {fn!r}")
        if value is None:
            raise ValueError("value must be a callable f(x) of points (..., 3) returning shape (...)")
        self._value = value
        self._gradient = gradient
        self._hessian = hessian
        self.lipschitz = None if lipschitz is None else _positive(lipschitz, "lipschitz")
        self.is_distance = bool(is_distance)
        self.area = None if area is None else _positive(area, "area")
        self.volume = None if volume is None else _positive(volume, "volume")
        self.step = None if step is None else _positive(step, "step")
        if bounds is not None:
            lo, hi = (np.asarray(b, dtype=float) for b in bounds)
            if lo.shape != (3,) or hi.shape != (3,) or not np.all(lo <= hi):
                raise ValueError(
                    f"bounds must be (lower (3,), upper (3,)) with lower <= upper, got {bounds!r}"
                )
            self._bounds = (lo, hi)
        else:
            self._bounds = None

    def __repr__(self) -> str:
        return (f"FunctionLevelSet({getattr(self._value, '__name__', 'f')}, "
                f"is_distance={self.is_distance}, lipschitz={self.lipschitz})")

    def bounds(self):
        """The bounding box given at construction, or None."""
        return self._bounds

    def _call(self, fn, x, tail, name):
        out = np.asarray(fn(x), dtype=float)
        expected = x.shape[:-1] + tail
        if out.shape != expected:
            raise ValueError(
                f"{name}(x) returned shape {out.shape} for x of shape {x.shape}; it must return "
                f"{expected}: write it vectorized over the leading axes, e.g. use x[..., 0] and "
                "reductions along axis=-1"
            )
        return out

    def _h(self, x, power):
        if self.step is not None:
            return np.full(x.shape[:-1], self.step)
        scale = np.maximum(1.0, np.max(np.abs(x), axis=-1))
        return _EPS**power * scale

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
        h = self._h(x, 0.25)
        eye = np.eye(3)
        # sign pattern (+,+), (+,-), (-,+), (-,-) for each pair (i, j): shape (4, 3, 3, 3)
        signs = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=float)
        shifts = signs[:, 0, None, None, None] * eye[None, :, None, :] \
            + signs[:, 1, None, None, None] * eye[None, None, :, :]  # (4, i, j, 3)
        xs = x[..., None, None, None, :] + h[..., None, None, None, None] * shifts
        f = self._call(self._value, xs, (), "value")  # (..., 4, 3, 3)
        hess = (f[..., 0, :, :] - f[..., 1, :, :] - f[..., 2, :, :] + f[..., 3, :, :]) \
            / (4.0 * h[..., None, None] ** 2)
        return 0.5 * (hess + np.swapaxes(hess, -1, -2))

    def closest_point(self, x):
        """x - phi(x) grad phi(x) when is_distance (exact for a signed distance), shape (..., 3).

        NotImplementedError for a general level set.
        """
        if not self.is_distance:
            return super().closest_point(x)
        x = _as_points(x)
        return x - self.value(x)[..., None] * self.gradient(x)


# ----------------------------------------------------------------------------------------------
# triangle mesh
# ----------------------------------------------------------------------------------------------
def _surface_arrays(surface):
    """(points (N, 3) float64, triangles (M, 3) int64) from a PolyData or a points/triangles object."""
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
    return pts, tris


class SignedDistance(LevelSet):
    """Signed distance to a closed, consistently oriented triangle mesh (negative inside).

    Values come from VTK's vtkImplicitPolyDataDistance (closest point on the triangles, signed by
    the outward normals) evaluated on a whole vtk array at once (C++ loop, no Python loop).

    The mesh is checked on construction: every undirected edge must belong to exactly two
    triangles (closed, manifold) and every directed edge to exactly one (consistent orientation);
    otherwise ValueError.  If the enclosed signed volume (1/6 sum_T p0 . (p1 x p2)) is negative
    the orientation is reversed so that normals point outward.  Degenerate (zero-area) triangles
    are rejected.

    gradient: central differences of value with h = 1e-6 * (mesh bounding-box diagonal); this is
    the exact gradient wherever the distance is smooth over the stencil (away from the medial set
    and from points within h of a mesh edge or vertex).
    closest_point: x - phi(x) grad phi(x), exact where the gradient is.
    The Hessian (and hence curvature) of a polyhedral distance carries no curvature information:
    hessian raises NotImplementedError.  ``area`` and ``volume`` are those of the polyhedron,
    lipschitz 1, is_distance True, bounds the points' bounding box.
    """

    is_distance = True
    lipschitz = 1.0

    def __init__(self, surface):
        import pyvista as pv
        import vtk

        pts, tris = _surface_arrays(surface)
        p0, p1, p2 = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
        cross = np.cross(p1 - p0, p2 - p0)
        twice_area = np.linalg.norm(cross, axis=1)
        diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
        degenerate = twice_area <= 1e-14 * diag**2
        if degenerate.any():
            raise ValueError(
                f"surface has {int(degenerate.sum())} degenerate (zero-area) triangle(s) "
                f"(first: index {int(np.flatnonzero(degenerate)[0])}); remove them, e.g. "
                "surface.clean(), before building a SignedDistance"
            )
        directed = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
        undirected = np.sort(directed, axis=1)
        _, counts = np.unique(undirected, axis=0, return_counts=True)
        if np.any(counts != 2):
            raise ValueError(
                f"surface is not a closed manifold triangle mesh: {int(np.sum(counts == 1))} "
                f"boundary edge(s) and {int(np.sum(counts > 2))} edge(s) shared by more than two "
                "triangles; close the mesh (or merge duplicate points with surface.clean())"
            )
        _, dcounts = np.unique(directed, axis=0, return_counts=True)
        if np.any(dcounts != 1):
            raise ValueError(
                f"surface triangles are not consistently oriented ({int(np.sum(dcounts != 1))} "
                "directed edge(s) used twice); orient them, e.g. "
                "surface.compute_normals(consistent_normals=True, auto_orient_normals=True)"
            )
        signed_volume = float(np.einsum("ij,ij->", p0, np.cross(p1, p2))) / 6.0
        if signed_volume < 0.0:
            tris = tris[:, ::-1].copy()
            signed_volume = -signed_volume

        self.points = pts
        self.triangles = tris
        self.area = float(0.5 * twice_area.sum())
        self.volume = signed_volume
        self._diag = diag
        cells = np.hstack([np.full((len(tris), 1), 3, dtype=np.int64), tris]).ravel()
        self._mesh = pv.PolyData(pts, faces=cells)
        self._implicit = vtk.vtkImplicitPolyDataDistance()
        self._implicit.SetInput(self._mesh)

    def __repr__(self) -> str:
        return f"SignedDistance(<{len(self.points)} points, {len(self.triangles)} triangles>)"

    def bounds(self):
        """Bounding box of the mesh points, (lower (3,), upper (3,))."""
        return self.points.min(axis=0), self.points.max(axis=0)

    def value(self, x):
        """Signed distance to the mesh (negative inside), shape (...)."""
        import vtk
        from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy

        x = _as_points(x)
        flat = np.ascontiguousarray(x.reshape(-1, 3))
        if flat.shape[0] == 0:
            return np.zeros(x.shape[:-1])
        out = vtk.vtkDoubleArray()
        self._implicit.FunctionValue(numpy_to_vtk(flat, deep=True), out)
        return vtk_to_numpy(out).astype(float, copy=True).reshape(x.shape[:-1])

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
        """x - phi(x) grad phi(x), shape (..., 3) (exact where the distance is smooth)."""
        x = _as_points(x)
        return x - self.value(x)[..., None] * self.gradient(x)


# ----------------------------------------------------------------------------------------------
# nodal interpolation
# ----------------------------------------------------------------------------------------------
def interpolate(levelset: LevelSet, points) -> np.ndarray:
    """Nodal values phi(x_i) of a level set at points (n, 3); returns (n,) float64.

    This is the nodal interpolant rho_h of SPEC section 2 given by its nodal values.  ValueError
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
