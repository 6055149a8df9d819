"""The named level sets with closed forms: :class:`Sphere`, :class:`Torus`, :class:`Ellipsoid` and :class:`Plane`.

Each overrides the general machinery of :class:`~cutfem.geometry.levelset.LevelSet` with its exact
formulas: values, derivatives, the closest point and the exact normal and mean curvature there
(docs/math.md §1).  Sphere, Torus and Plane are signed distances; the Ellipsoid is the quadratic
(x/a)^2 + (y/b)^2 + (z/c)^2 - 1, whose closest point comes from Newton's method on the Lagrange
multiplier of the projection.  Their lengths must lie in :data:`cutfem.geometry.surface.LENGTH_RANGE`.
"""

from __future__ import annotations

import numpy as np

from .levelset import _EPS, LevelSet, _as_points, _raise_if_singular
from .surface import check_length
from . import levelset_kernels

__all__ = ["Sphere", "Torus", "Ellipsoid", "Plane"]


def _center(center, name: str = "center") -> np.ndarray:
    """Return ``center`` as a float array of shape (3,), ValueError naming it otherwise."""
    c = np.asarray(center, dtype=float)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise ValueError(f"{name} must be 3 finite coordinates, got {center!r}")
    return c


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
# plane
# ----------------------------------------------------------------------------------------------
class Plane(LevelSet):
    """The plane through the point p with unit normal n, as its signed distance phi(x) = n . (x - p):
    the half-space {phi < 0} lies behind the normal, which points out of it.

    A P1 interpolant reproduces it exactly, so its cut is exact on any mesh.  grad phi = n,
    Hess phi = 0, p(x) = x - phi(x) n, mean curvature 0; lipschitz 1.  A plane is not a closed
    surface: it bounds a domain only together with other level sets (a ball cut by a half-space,
    a cube from six planes: :func:`cutfem.geometry.csg.intersection`), and it has no bounding box.
    ``normal``: any nonzero vector (normalized here); ``point``: a point of the plane.
    """

    is_distance = True
    lipschitz = 1.0

    def __init__(self, normal=(0.0, 0.0, 1.0), point=(0.0, 0.0, 0.0)):
        n = _center(normal, "Plane: the normal")
        length = float(np.linalg.norm(n))
        if not length > 0:
            raise ValueError(f"Plane: the normal must be a nonzero vector, got {normal!r}")
        self.normal_vector = n / length
        self.point = _center(point, "Plane: the point")

    def __repr__(self) -> str:
        return f"Plane(normal={tuple(self.normal_vector.tolist())!r}, point={tuple(self.point.tolist())!r})"

    def value(self, x):
        """n . (x - p), shape (...)."""
        x = _as_points(x)
        return (x - self.point) @ self.normal_vector

    def gradient(self, x):
        """n, shape (..., 3)."""
        x = _as_points(x)
        return np.broadcast_to(self.normal_vector, x.shape).copy()

    def hessian(self, x):
        """0, shape (..., 3, 3)."""
        x = _as_points(x)
        return np.zeros(x.shape + (3,))

    def closest_point(self, x):
        """x - phi(x) n, shape (..., 3)."""
        x = _as_points(x)
        return x - self.value(x)[..., None] * self.normal_vector

    def exact_normal(self, x):
        return self.gradient(x)

    def exact_mean_curvature(self, x):
        return np.zeros(_as_points(x).shape[:-1])

    def exact_mean_curvature_vector(self, x):
        return np.zeros(_as_points(x).shape)


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
