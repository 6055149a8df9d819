"""Independent references for the level-set tests (tests/geometry/test_levelset.py, test_shapes.py,
test_signed_distance.py): central differences, random unit directions, explicit parametrizations
of the torus and the ellipsoid with the normal and k1 + k2 from their fundamental forms, and a
tensor quadrature of parametric area elements.  None of them uses the code under test."""

import numpy as np


def fd_gradient(f, x, h=1e-6):
    """Central differences of a scalar field f at x (n, 3) -> (n, 3)."""
    cols = [(f(x + h * e) - f(x - h * e)) / (2 * h) for e in np.eye(3)]
    return np.stack(cols, axis=-1)


def fd_jacobian(g, x, h=1e-6):
    """Central differences of a vector field g at x (n, 3) -> J (n, 3, 3), J[:, i, j] = dg_i/dx_j."""
    cols = [(g(x + h * e) - g(x - h * e)) / (2 * h) for e in np.eye(3)]
    return np.stack(cols, axis=-1)


def parametric_geometry(r_u, r_v, r_uu, r_uv, r_vv, outward_hint):
    """Outward unit normal and k1 + k2 from the fundamental forms of a parametrization.

    k1 + k2 = -(e G - 2 f F + g E) / (E G - F^2) with the outward normal (2/R on a sphere).
    """
    n = np.cross(r_u, r_v)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n *= np.sign(np.sum(n * outward_hint, axis=-1))[:, None]
    E, F, G = (np.sum(a * b, axis=-1) for a, b in ((r_u, r_u), (r_u, r_v), (r_v, r_v)))
    e, f, g = (np.sum(a * n, axis=-1) for a in (r_uu, r_uv, r_vv))
    return n, -(e * G - 2 * f * F + g * E) / (E * G - F**2)


def torus_param(R, r, t, p):
    """Point, derivatives and outward hint of the torus of docs/math.md parametrization."""
    ct, st, cp, sp = np.cos(t), np.sin(t), np.cos(p), np.sin(p)
    rho = R + r * cp
    x = np.stack([rho * ct, rho * st, r * sp], axis=-1)
    r_t = np.stack([-rho * st, rho * ct, 0 * t], axis=-1)
    r_p = np.stack([-r * sp * ct, -r * sp * st, r * cp], axis=-1)
    r_tt = np.stack([-rho * ct, -rho * st, 0 * t], axis=-1)
    r_tp = np.stack([r * sp * st, -r * sp * ct, 0 * t], axis=-1)
    r_pp = np.stack([-r * cp * ct, -r * cp * st, -r * sp], axis=-1)
    core = np.stack([R * ct, R * st, 0 * t], axis=-1)
    return x, r_t, r_p, r_tt, r_tp, r_pp, x - core


def ellipsoid_param(a, b, c, th, ph):
    """Point, derivatives and outward hint of (a sin th cos ph, b sin th sin ph, c cos th)."""
    s, co, sp, cp = np.sin(th), np.cos(th), np.sin(ph), np.cos(ph)
    x = np.stack([a * s * cp, b * s * sp, c * co], axis=-1)
    r_t = np.stack([a * co * cp, b * co * sp, -c * s], axis=-1)
    r_p = np.stack([-a * s * sp, b * s * cp, 0 * th], axis=-1)
    r_tt = np.stack([-a * s * cp, -b * s * sp, -c * co], axis=-1)
    r_tp = np.stack([-a * co * sp, b * co * cp, 0 * th], axis=-1)
    r_pp = np.stack([-a * s * cp, -b * s * sp, 0 * th], axis=-1)
    return x, r_t, r_p, r_tt, r_tp, r_pp, x


def tensor_quadrature(n_u, n_v, u_range, periodic_v=True):
    """Gauss-Legendre in u on u_range times the trapezoid rule in a periodic v on [0, 2 pi)."""
    xg, wg = np.polynomial.legendre.leggauss(n_u)
    lo, hi = u_range
    u = 0.5 * (hi - lo) * xg + 0.5 * (hi + lo)
    wu = 0.5 * (hi - lo) * wg
    v = 2 * np.pi * np.arange(n_v) / n_v
    wv = np.full(n_v, 2 * np.pi / n_v)
    U, V = np.meshgrid(u, v, indexing="ij")
    return U.ravel(), V.ravel(), np.outer(wu, wv).ravel()


def random_directions(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)
