"""Error functionals and convergence rates (docs/math.md §5).

* :func:`l2_error`: ``sqrt( sum over S_h of |u^e - u_h|^2 )`` by quadrature of degree >= 4 on every
  triangle of S_h (quadrilateral pieces are two triangles).
* :func:`h1_error`: ``|| grad_{S_h} u^e - grad_{S_h} u_h ||_{S_h}`` with ``grad_{S_h} = P_h grad``
  (over a volume measure: the full gradient).
* :func:`l2_h1_errors`: both in one pass over the cells, from an exact solution that returns the
  pair (u, grad u).
* :func:`discrete_error`: ``|| pi_h u - u_h ||_{S_h}``, the L2(S_h) norm of a discrete function
  from its values at the vertices of S_h (exact for P1: sqrt(e^T M e) without the matrix M).
* :func:`rates`: ``log(e_i / e_{i+1}) / log(h_i / h_{i+1})``; :func:`fitted_rate`: least-squares
  slope of log e against log h.

Every error takes one field (a :class:`~cutfem.fem.spaces.CutSpace`,
:class:`~cutfem.fem.spaces.SurfaceP1Space` or :class:`~cutfem.fem.spaces.VectorSpace`, not a
:class:`~cutfem.fem.spaces.ProductSpace`) and its coefficients of shape (n_dofs,) or (n_dofs, c)
(:func:`_field_coefficients`, on every path): the block of a product's vector is ``W.split(x)[k]``.
A vector field's coefficients (3 n,) are its scalar space's nodal vectors (n, 3), so its exact
solution returns (m, q, 3) and its gradient (m, q, 3, 3), rows the components (grad u)_ij = d u_i / d x_j.  A measure must lie on the field's background mesh
(:meth:`~cutfem.fem.spaces.CutSpace.local_elements`).
"""

from __future__ import annotations

import numpy as np

from ..geometry.measures import surface_measure
from ..geometry.mesh import triangle_areas
from ..geometry.quadrature import triangle_rule
from . import element_kernels, p2_kernels
from .spaces import ProductSpace, VectorSpace

__all__ = ["l2_error", "h1_error", "l2_h1_errors", "discrete_error", "rates", "fitted_rate", "surface_integral"]

_ZERO = np.zeros((0, 0, 0))  # no exact field: element_kernels.squared_error gives the norm of u_h itself


def _field_coefficients(space, coeffs):
    """(scalar space, coefficients (n_dofs,) or (n_dofs, c)) of the one field ``space``: a vector
    field's are its scalar space and nodal vectors (n, 3); a ValueError for a product space (errors
    are per field) or for any other shape (``space._coefficients``)."""
    if isinstance(space, ProductSpace):
        raise ValueError(f"errors are computed per field, and this is a product space of the fields {space.names}: pass "
                         "one field and its block, e.g. l2_error(W[k], W.split(x)[k], exact, measure)")
    if isinstance(space, VectorSpace):
        return space.scalar, space.nodal(coeffs)
    return space, space._coefficients(coeffs)


def _not_finite(part: float, exact_values, coeffs, points, what: str) -> None:
    """Raise a ValueError naming the cause when a block's sum ``part`` is not finite: the exact
    function's values (``exact_values`` at ``points`` (m, q, 3)) or the discrete coefficients.
    Checked only then, so a finite sum costs nothing more."""
    if np.isfinite(part):
        return
    values = np.asarray(exact_values, dtype=float)
    bad = ~np.isfinite(values.reshape(values.shape[:2] + (-1,))).all(axis=2)
    if bad.any():
        i, j = (int(k[0]) for k in np.nonzero(bad))
        raise ValueError(f"the {what} is not finite at {int(bad.sum())} quadrature point(s), e.g. x = {points[i, j].tolist()}: "
                         "check where it is defined (the error would be nan)")
    count = int(np.count_nonzero(~np.isfinite(np.asarray(coeffs, dtype=float))))
    raise ValueError(f"the discrete coefficients are not finite ({count} of them): the solve or the data that made them "
                     "failed; the error would be nan or inf" if count else
                     f"the error sum overflows (the {what} or the coefficients are too large for float64)")


def _error_degree(space, degree):
    """The quadrature degree of an error norm: ``degree``, or 4 + 2 (order - 1) on a field of that
    order (docs/math.md §5 asks for at least 4: the P1 errors' degree)."""
    if degree is None:
        return 4 + 2 * (getattr(space, "order", 1) - 1)
    if degree < 4:
        raise ValueError("docs/math.md §5 asks for quadrature of degree >= 4 in error norms")
    return degree


def l2_error(space, coeffs, exact, measure=None, degree: int | None = None, chunk: int = 1 << 14) -> float:
    """L2 error of the discrete function ``coeffs`` (n,) or (n, c) against ``exact(x)`` over ``measure``
    (any cell measure of :mod:`cutfem.geometry.measures`; ``None``: S_h of a trace or meshed field).

    ``exact`` maps points (m, q, 3) to (m, q) or (m, q, c), and is evaluated at the quadrature
    points of S_h (so it must already be the extension, e.g. H o p).  On S_h, u_h is linear on each
    triangle (a triangle lies in one element), so its values at the quadrature points are the
    barycentric combinations of its values at the triangle's vertices:

        x_q = sum_v b_qv x_v,  u_h(x_q) = sum_v b_qv u_v,
        error^2 = sum_T |T| sum_q w_q |u^e(x_q) - u_h(x_q)|^2,

    (b, w) the reference rule of the given degree, |T| = |(x_1 - x_0) x (x_2 - x_0)| / 2.  The
    triangles go in blocks of ``chunk``: per block one call of ``exact`` on all its points, the
    points and the sum by compiled kernels (:func:`cutfem.fem.element_kernels.triangle_points`,
    :func:`cutfem.fem.element_kernels.squared_error`).  Over a ``measure``: the cells in blocks of
    :data:`CELL_CHUNK`, as :func:`l2_h1_errors`.
    """
    degree = _error_degree(space, degree)
    if measure is None and getattr(space, "order", 1) == 1:
        space, coeffs = _field_coefficients(space, coeffs)
        surface_measure(space)  # a clear error for a bulk field
        points, triangles, values = space.surface_vertex_data(coeffs)
        points = np.ascontiguousarray(points, dtype=float)
        values = np.ascontiguousarray(np.asarray(values, dtype=float).reshape(len(values), -1))
        bary, w = triangle_rule(degree)
        bary, w = np.ascontiguousarray(bary, dtype=float), np.ascontiguousarray(w, dtype=float)
        q, c = len(w), values.shape[1]
        total = 0.0
        for start in range(0, len(triangles), chunk):  # blocks of triangles, not single elements
            t = np.ascontiguousarray(triangles[start : start + chunk])
            x, area = np.empty((len(t), q, 3)), np.empty(len(t))
            element_kernels.triangle_points(points, t, bary, x, area)
            ue = np.asarray(exact(x), dtype=float)
            if ue.size != len(t) * q * c:
                raise ValueError(f"the exact solution must give {c} value(s) per point at points {x.shape}, got shape {ue.shape}")
            part = element_kernels.squared_error(values, t, bary, w, area, np.ascontiguousarray(ue.reshape(len(t), q, c)))
            _not_finite(part, ue.reshape(len(t), q, c), values, x, "exact solution")
            total += part
        return float(np.sqrt(total))
    return _cell_errors(space, coeffs, lambda x: (exact(x), None), measure, degree, CELL_CHUNK)[0]


#: cells per block of the volume and cut-cell error sums
CELL_CHUNK = 1 << 13


def h1_error(space, coeffs, exact_gradient, measure=None, degree: int | None = None, chunk: int = CELL_CHUNK) -> float:
    """H1 seminorm error of a discrete function: ``|| grad u^e - grad u_h ||`` over a volume
    measure, ``|| P_h (grad u^e - grad u_h) ||`` over a surface (``measure=None``: S_h of a trace or
    meshed field).  ``exact_gradient(x)`` maps (m, q, 3) to (m, q, 3), for a vector field (or
    coefficients (n, c)) to (m, q, c, 3), the gradients of the components as rows.  Cells in blocks
    of ``chunk`` (see :func:`l2_error`)."""
    return _cell_errors(space, coeffs, lambda x: (None, exact_gradient(x)), measure, degree, chunk)[1]


def l2_h1_errors(space, coeffs, exact, measure=None, degree: int | None = None, chunk: int = CELL_CHUNK) -> tuple[float, float]:
    """(L2 error, H1 seminorm error) of a discrete function in one pass over the cells:
    the values of :func:`l2_error` and :func:`h1_error` (the same quadrature, the same sums), with
    ``exact(x)`` returning the pair ``(u(x) (m, q), grad u(x) (m, q, 3))`` at points (m, q, 3)
    (of a vector field ``(u(x) (m, q, 3), grad u(x) (m, q, 3, 3))``).

    One pass maps each block's quadrature points once, and lets ``exact`` share its work between u
    and grad u (a product of sines, cosines and exponentials needs each factor once): on the
    fictitious-domain Poisson problem at 292k unknowns (22 million points) that is about a third of
    the time of the two separate calls.  Anything but a pair from ``exact`` is refused (ValueError)."""

    def pair(x):
        out = exact(x)
        if not isinstance(out, (tuple, list)) or len(out) != 2:
            got = f"a {type(out).__name__} of length {len(out)}" if isinstance(out, (tuple, list)) else \
                f"{type(out).__name__} of shape {np.shape(out)}"
            raise ValueError(f"l2_h1_errors: exact(x) must return the pair (u(x) of shape (m, q), grad u(x) of shape "
                             f"(m, q, 3)) at points x {x.shape}, got {got}; for one of them use l2_error or h1_error")
        return out

    return _cell_errors(space, coeffs, pair, measure, degree, chunk)


def _cell_errors(space, coeffs, exact, measure, degree, chunk):
    """(sqrt sum |u^e - u_h|^2, sqrt sum |grad u^e - grad u_h|^2 (tangential on a surface)) by
    quadrature over the cells of ``measure`` in blocks of ``chunk``; ``exact(x)`` returns the pair
    (values or None, gradients or None); a sum whose exact part is None stays 0.

    Per block: u_h(x_q) = sum_k phi_k(x_q) u_k with the basis values of the block
    (:meth:`~cutfem.fem.spaces.CutSpace.basis_on`: the rule's barycentric coordinates on whole
    elements), grad u_h = sum_k u_k grad phi_k (constant per element); the sums over a block by
    compiled kernels (:func:`cutfem.fem.element_kernels.cell_value_error`, :func:`cutfem.fem.element_kernels.cell_gradient_error`:
    on the fictitious-domain Poisson problem at spacing 0.025, 352 thousand unknowns and 31.8
    million points, they replace numpy work of about 0.6 s)."""
    degree = _error_degree(space, degree)
    space, coeffs = _field_coefficients(space, coeffs)
    if measure is None:
        measure = surface_measure(space)

    table, types = space.gradient_lookup()  # the gradients of element K: table[types[K]]
    table = np.ascontiguousarray(table, dtype=float)
    sums = [0.0, 0.0]
    no_normals = np.zeros((0, 3))
    for _, quad in measure.blocks(degree, chunk):  # blocks of cells, not single elements
        ue, ge = exact(quad.points)
        e = space.local_elements(measure, quad.parent)
        local = coeffs[np.take(space.element_dofs, e, axis=0)]  # (b, k) or (b, k, c); take: rows gathered 2.5x faster
        weights = np.ascontiguousarray(quad.weights, dtype=float)
        if ue is not None:
            phi = space.basis_on(measure, quad, e)
            shape = phi.shape[:2] + local.shape[2:]
            ue = np.asarray(ue, dtype=float)
            if ue.shape != shape:
                raise ValueError(f"the exact solution must have shape {shape} at points {quad.points.shape}, got {ue.shape}")
            local3 = np.ascontiguousarray(local, dtype=float).reshape(local.shape[:2] + (-1,))
            phi = np.ascontiguousarray(phi[:1] if phi.strides[0] == 0 else phi, dtype=float)  # whole cells: one table
            part = element_kernels.cell_value_error(phi, local3, np.ascontiguousarray(ue.reshape(shape[:2] + (-1,))), weights)
            _not_finite(part, ue, coeffs, quad.points, "exact solution")
            sums[0] += part
        if ge is not None:
            x = quad.points
            ge = np.asarray(ge, dtype=float)
            shape = x.shape[:2] + local.shape[2:] + (3,)
            if ge.shape != shape:
                raise ValueError(f"the exact gradient must have shape {shape} at points {x.shape} (the gradient of each "
                                 f"component as a row), got {ge.shape}")
            if space.order > 1 or quad.jacobians is not None:  # gradients that vary over the cell
                sums[1] += _varying_gradient_error(space, measure, quad, e, local, ge, coeffs)
                continue
            normals = np.ascontiguousarray(quad.normal, dtype=float) if measure.surface else no_normals
            kinds = np.ascontiguousarray(types[e])
            for c in range(1 if local.ndim == 2 else local.shape[2]):  # the components' errors, summed
                lc, gc = (local, ge) if local.ndim == 2 else (local[:, :, c], ge[:, :, c])
                part = element_kernels.cell_gradient_error(table, kinds, np.ascontiguousarray(lc, dtype=float),
                                                           np.ascontiguousarray(gc), weights, normals)
                _not_finite(part, gc, coeffs, x, "exact gradient")
                sums[1] += part
    return float(np.sqrt(sums[0])), float(np.sqrt(sums[1]))


def _varying_gradient_error(space, measure, quad, elements, local, exact_gradient, coeffs) -> float:
    """sum_q w_q |grad u^e - grad u_h|^2 (tangential on a surface) over a block of cells, with the
    basis gradients made at each point by a compiled kernel (:func:`cutfem.fem.p2_kernels.gradient_errors`:
    P2, or a deformed geometry), one sum per cell, then summed in cell order."""
    L = np.ascontiguousarray(local if local.ndim == 3 else local[..., None], dtype=float)  # (b, k, c)
    ge = np.ascontiguousarray(exact_gradient if local.ndim == 3 else exact_gradient[:, :, None], dtype=float)
    lam = space._barycentric_on(measure, quad, elements) if space.order > 1 else np.empty((len(elements), 1, 4))
    jac = np.empty((0, 1, 3, 3)) if quad.jacobians is None else quad.jacobians
    normals = np.ascontiguousarray(quad.point_normals, dtype=float) if measure.surface else np.empty((0, 1, 3))
    cells = np.empty(len(elements))
    p2_kernels.gradient_errors(np.ascontiguousarray(lam, dtype=float), np.ascontiguousarray(space.gradients_of(elements), dtype=float),
                               np.ascontiguousarray(jac), L, ge, np.ascontiguousarray(quad.weights, dtype=float), normals, cells)
    part = float(np.sum(cells))
    _not_finite(part, exact_gradient, coeffs, quad.points, "exact gradient")
    return part


def discrete_error(space, e) -> float:
    """||e_h||_{L2(S_h)} of the discrete function with coefficients e (n,) or (n, c) (components
    summed) on the surface of ``space``: with e = pi_h u - u_h the discrete error
    ||pi_h u - u_h||_{S_h} = sqrt(e^T M e), M the P1 mass matrix on S_h, computed without M: e_h is
    linear on every (planar) triangle T of S_h, so e_h^2 is a quadratic there, integrated exactly by
    the three-point rule of degree 2 (:func:`cutfem.geometry.quadrature.triangle_rule`), which gives

        int_T e_h^2 = |T| / 12 (e_1^2 + e_2^2 + e_3^2 + (e_1 + e_2 + e_3)^2)

    (the P1 mass matrix of a triangle, |T| / 12 [[2, 1, 1], [1, 2, 1], [1, 1, 2]]) up to rounding, in
    one compiled pass over the triangles (:func:`cutfem.fem.element_kernels.squared_error` against zero).  For
    a cut space the values at the vertices are the traces of the field (:meth:`surface_vertex_data`)."""
    space, e = _field_coefficients(space, e)
    measure = surface_measure(space)  # a clear error for a bulk field
    if space.order > 1:  # e_h^2 of degree 4 on each triangle: the rule of that degree, exact
        values = space.evaluate(np.asarray(e, dtype=float), measure, 4)
        weights = measure.quadrature(4).weights
        return float(np.sqrt(np.sum(weights * np.sum(values.reshape(weights.shape + (-1,)) ** 2, axis=2))))

    points, triangles, values = space.surface_vertex_data(np.asarray(e, dtype=float))
    v = np.asarray(values, dtype=float)
    triangles = np.ascontiguousarray(triangles)
    bary, w = triangle_rule(2)
    total = element_kernels.squared_error(np.ascontiguousarray(v.reshape(v.shape[0], -1)), triangles, bary, w,
                                  triangle_areas(points, triangles), _ZERO)
    return float(np.sqrt(max(total, 0.0)))


def surface_integral(space, coeffs) -> np.ndarray:
    """Integral over S_h of a discrete function: scalar or (c,) vector.  Exact: a linear function
    integrates over a triangle to its area times the mean of its vertex values (P2: the rule of
    degree 2 on each triangle)."""
    space, coeffs = _field_coefficients(space, coeffs)
    measure = surface_measure(space)  # a clear error for a bulk field
    if space.order > 1:
        values = space.evaluate(np.asarray(coeffs, dtype=float), measure, 2)
        return np.einsum("mq,mq...->...", measure.quadrature(2).weights, values)
    points, triangles, values = space.surface_vertex_data(coeffs)
    area = triangle_areas(points, triangles)
    return np.einsum("m,mk...->...", area / 3.0, np.asarray(values)[triangles])


def _levels(h, errors, what: str):
    """(h, e) as float arrays of one length, checked: h positive and finite, every error positive
    and finite or missing (None or NaN, kept as NaN); a ValueError naming the first bad entry."""
    if np.ndim(h) != 1 or np.ndim(errors) != 1 or len(h) != len(errors):
        raise ValueError(f"{what}: h and errors must be two sequences of the same length, got shapes {np.shape(h)} and "
                         f"{np.shape(errors)}")
    h = np.asarray(h, dtype=float)
    e = np.array([np.nan if v is None else v for v in errors], dtype=float)
    bad = ~(np.isfinite(h) & (h > 0))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{what}: every h must be positive and finite, got h[{i}] = {h[i]}")
    bad = ~np.isnan(e) & ~(np.isfinite(e) & (e > 0))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{what}: an error must be positive and finite (or None/NaN for a level without it), got "
                         f"errors[{i}] = {e[i]}")
    return h, e


def rates(h, errors) -> np.ndarray:
    """Rates between consecutive levels, log(e_i/e_{i+1}) / log(h_i/h_{i+1}); length len(h) - 1.

    ``h`` and ``errors``: sequences of one length, h positive and finite with no two consecutive
    levels equal, the errors positive and finite; an error that is missing (None or NaN: a level
    without it) gives NaN for the rates next to it.  Anything else raises a ValueError."""
    h, e = _levels(h, errors, "rates")
    same = h[:-1] == h[1:]
    if same.any():
        i = int(np.flatnonzero(same)[0])
        raise ValueError(f"rates: consecutive levels need different h, got h[{i}] = h[{i + 1}] = {h[i]}")
    return np.log(e[:-1] / e[1:]) / np.log(h[:-1] / h[1:])


def fitted_rate(h, errors) -> float:
    """Least-squares slope of log(error) against log(h) over the levels with an error (missing
    errors, None or NaN, are left out).  ``h`` and ``errors`` as for :func:`rates`; the fit needs
    at least two levels with an error and two distinct h among them, else a ValueError."""
    h, e = _levels(h, errors, "fitted_rate")
    have = ~np.isnan(e)
    if len(np.unique(h[have])) < 2:
        raise ValueError(f"fitted_rate: a fit needs errors at two levels of different h at least, got {int(have.sum())} "
                         f"error(s) at h = {h[have].tolist()}")
    return float(np.polyfit(np.log(h[have]), np.log(e[have]), 1)[0])
