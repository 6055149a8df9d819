"""Closed forms and fast paths of the meshed (triangulated surface) pipeline.

Each fast path is checked against the general route it replaces: the same numbers up to
round-off, on meshes where nothing is special (perturbed and flipped tori, the icosahedral sphere).
"""

import numpy as np
import pytest

from cutfem.errors import l2_error
from cutfem.levelset import Torus
from cutfem.spaces import SurfaceP1Space
from cutfem.surface import sphere_mesh, torus_mesh


def test_torus_mean_curvature_vector_closed_form_matches_frame():
    tor = Torus(1.3, 0.45, center=[0.1, -0.2, 0.3])
    rng = np.random.default_rng(7)
    x = tor.center + rng.uniform(-1.8, 1.8, size=(4, 50, 3)) * [1, 1, 0.5]
    expected = tor.exact_mean_curvature(x)[..., None] * tor.exact_normal(x)
    np.testing.assert_allclose(tor.exact_mean_curvature_vector(x), expected, rtol=1e-13, atol=1e-13)
    with pytest.raises(ValueError, match="axis"):
        tor.exact_mean_curvature_vector(tor.center + np.array([[0.0, 0.0, 0.2]]))
    with pytest.raises(ValueError, match="core circle"):
        tor.exact_mean_curvature_vector(tor.center + np.array([[1.3, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="NaN"):
        tor.exact_mean_curvature_vector(np.array([[np.nan, 0.0, 0.0]]))


def _l2_by_quadrature(space, coeffs, exact, degree=4):
    """The general route: the space's quadrature, u_h from the P1 basis values."""
    quad = space.quadrature("surface", degree)
    d = np.asarray(exact(quad.points)) - space.evaluate(coeffs, quad)
    d = d.reshape(d.shape[0], d.shape[1], -1)
    return np.sqrt(np.einsum("mqc,mqc,mq->", d, d, quad.weights))


@pytest.mark.parametrize("chunk", [1000, 1 << 12])
def test_l2_error_blocks_match_quadrature(chunk):
    space = SurfaceP1Space(torus_mesh(40, "perturbed-flipped", seed=3))
    tor = Torus()
    H = np.cos(3 * space.dof_points)  # vector valued
    expected = _l2_by_quadrature(space, H, tor.exact_mean_curvature_vector)
    assert l2_error(space, H, tor.exact_mean_curvature_vector, chunk=chunk) == pytest.approx(expected, rel=1e-13)
    u = np.sin(space.dof_points[:, 0])  # scalar, degree 6
    f = lambda x: x[..., 0] * x[..., 1]  # noqa: E731
    expected = _l2_by_quadrature(space, u, f, degree=6)
    assert l2_error(space, u, f, degree=6, chunk=chunk) == pytest.approx(expected, rel=1e-13)
