"""Tests of cutfem.geometry.expressions: a level set written as text is checked before it is
evaluated, computes its constants in floating point, and never writes into the caller's points."""

import numpy as np
import pytest

from cutfem.geometry.levelset import FunctionLevelSet


@pytest.mark.parametrize("text", ["x**2 + y**2 + z**2 - 1 + 9**9**9", "x + 1/0", "x**2 + 10**400"])
def test_expression_constants_that_overflow_are_refused_at_once(text):
    """Integer literals are computed as floats: a tower of powers overflows at once (it would build
    a 370-million-digit integer), and so does a division by zero among the constants."""
    with pytest.raises(ValueError, match="cannot be evaluated"):
        FunctionLevelSet.from_expression(text).value(np.zeros((2, 3)))


def test_expression_integer_literals_keep_their_values():
    x = np.random.default_rng(0).normal(size=(50, 3))
    phi = FunctionLevelSet.from_expression("x**3 - 2*y**17 + 7/2 - z**2").value(x)
    np.testing.assert_allclose(phi, x[:, 0] ** 3 - 2 * x[:, 1] ** 17 + 3.5 - x[:, 2] ** 2, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("text,pattern", [
    ("hypot(x, y, z) - 1", "calls hypot with 3 argument"),  # numpy would write into z (the caller's array)
    ("abs(x, y)", "calls abs with 2 argument"),
    ("minimum(x)", "calls minimum with 1 argument"),
    ("sqrt()", "calls sqrt with 0 argument"),
    ("sin + x", "uses the function sin without calling it"),
    ("(-8)**(1/3) + x", "gives complex values"),
    ("+".join(["x"] * 2000), "nested too deeply"),
])
def test_expressions_with_wrong_calls_or_values_are_refused(text, pattern):
    p = np.array([[0.0, 0.0, 0.5], [0.6, 0.0, 0.8]])
    before = p.copy()
    with pytest.raises(ValueError, match=pattern):
        FunctionLevelSet.from_expression(text).value(p)
    np.testing.assert_array_equal(p, before)  # the caller's points are never written


def test_two_argument_functions_keep_working():
    p = np.array([[0.0, 0.0, 0.5], [0.6, 0.0, 0.8]])
    np.testing.assert_allclose(FunctionLevelSet.from_expression("hypot(hypot(x, y), z) - 1").value(p), [-0.5, 0.0], atol=1e-15)
