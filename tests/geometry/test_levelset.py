"""Tests of cutfem.geometry.levelset (the LevelSet base, FunctionLevelSet, interpolate) against
independent references: exact derivatives of a polynomial, central finite differences and random
directions (tests/levelset_references.py), and the closed forms of the sphere.
"""

import numpy as np
import pytest

from cutfem.geometry.levelset import FunctionLevelSet, LevelSet, interpolate
from cutfem.geometry.shapes import Sphere
from levelset_references import fd_gradient, fd_jacobian, random_directions

RNG_SEED = 20240601


# ----------------------------------------------------------------------------------------------
# a user's function: derivatives, closest point, bad shapes
# ----------------------------------------------------------------------------------------------
def _poly(x):
    return x[..., 0] ** 2 + 2 * x[..., 1] ** 2 + np.sin(x[..., 2]) + x[..., 0] * x[..., 1] * x[..., 2] - 1


def _poly_grad(x):
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    return np.stack([2 * x0 + x1 * x2, 4 * x1 + x0 * x2, np.cos(x2) + x0 * x1], axis=-1)


def _poly_hess(x):
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    two, four = np.full_like(x0, 2.0), np.full_like(x0, 4.0)
    return np.stack(
        [np.stack([two, x2, x1], -1), np.stack([x2, four, x0], -1), np.stack([x1, x0, -np.sin(x2)], -1)],
        axis=-2,
    )


def test_function_levelset_finite_differences_match_exact_derivatives():
    rng = np.random.default_rng(RNG_SEED)
    x = rng.uniform(-2, 2, size=(5, 6, 3))
    values_only = FunctionLevelSet(_poly)
    np.testing.assert_allclose(values_only.gradient(x), _poly_grad(x), atol=1e-8)
    np.testing.assert_allclose(values_only.hessian(x), _poly_hess(x), atol=2e-6)
    with_grad = FunctionLevelSet(_poly, gradient=_poly_grad)
    np.testing.assert_allclose(with_grad.hessian(x), _poly_hess(x), atol=1e-7)
    full = FunctionLevelSet(_poly, gradient=_poly_grad, hessian=_poly_hess)
    # the test's own central differences of the given callables
    flat = x.reshape(-1, 3)
    np.testing.assert_allclose(full.gradient(flat), fd_gradient(_poly, flat), atol=1e-7)
    np.testing.assert_allclose(full.hessian(flat), fd_jacobian(_poly_grad, flat), atol=1e-6)


def test_function_levelset_distance_closest_point_and_curvature():
    R = 0.8
    ls = FunctionLevelSet(lambda x: np.linalg.norm(x, axis=-1) - R, is_distance=True, lipschitz=1.0)
    rng = np.random.default_rng(RNG_SEED)
    x = random_directions(rng, 20) * rng.uniform(0.5, 1.5, size=(20, 1))
    np.testing.assert_allclose(ls.closest_point(x), R * x / np.linalg.norm(x, axis=1, keepdims=True), atol=1e-9)
    on = R * random_directions(rng, 20)
    np.testing.assert_allclose(ls.mean_curvature(on), 2 / R, rtol=1e-6)


def test_function_levelset_rejects_bad_shapes():
    bad = FunctionLevelSet(lambda x: np.linalg.norm(x, axis=-1, keepdims=True) - 1)
    with pytest.raises(ValueError, match="returned shape"):
        bad.value(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="returned shape"):
        FunctionLevelSet(_poly, gradient=lambda x: x[..., :2]).gradient(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="shape"):
        FunctionLevelSet(_poly).value(np.zeros((4, 2)))
    with pytest.raises(NotImplementedError, match="must implement value"):
        LevelSet().closest_point(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="lipschitz"):
        FunctionLevelSet(_poly, lipschitz=-1.0)


# ----------------------------------------------------------------------------------------------
# interpolate
# ----------------------------------------------------------------------------------------------
def test_interpolate_values_and_nan_detection():
    rng = np.random.default_rng(RNG_SEED)
    x = rng.uniform(-1, 1, size=(12, 3))
    np.testing.assert_allclose(interpolate(Sphere(0.5), x), np.linalg.norm(x, axis=1) - 0.5, atol=1e-15)
    with np.errstate(invalid="ignore"):
        ls = FunctionLevelSet(lambda y: np.sqrt(y[..., 0]) - 0.5)  # NaN where x < 0
        with pytest.raises(ValueError, match=r"NaN or infinite at \d+ of 12 point"):
            interpolate(ls, x)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        interpolate(Sphere(), x[:, :2])

