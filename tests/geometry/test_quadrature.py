"""Tests for cutfem.geometry.quadrature against closed-form moments.

Expected values come from exact formulas only:
* mean of a barycentric monomial over a d-simplex: alpha! d! / (|alpha| + d)!;
* int_0^1 t^k dt = 1 / (k + 1);
* for an affine l with vertex values l_0..l_d on a d-simplex T:
  int_T l^p = |T| p! d! / (p + d)! * sum_{|alpha| = p} prod_v l_v^alpha_v
  (expand l = sum_v l_v lambda_v with the multinomial theorem and use the moment above);
* int_T x x^T = |T| / ((d + 1)(d + 2)) (sum_v x_v x_v^T + (sum_v x_v)(sum_v x_v)^T).
"""

import itertools
import math

import numpy as np
import pytest

from cutfem.geometry.quadrature import (
    SEGMENT_MAX_DEGREE,
    TETRAHEDRON_MAX_DEGREE,
    TRIANGLE_MAX_DEGREE,
    Quadrature,
    concatenate,
    map_segments,
    map_tetrahedra,
    map_triangles,
    segment_rule,
    tetrahedron_rule,
    triangle_rule,
)


def multi_indices(n_vars, total):
    """All alpha in N^n_vars with |alpha| = total, shape (n, n_vars)."""
    return np.array(
        [a for a in itertools.product(range(total + 1), repeat=n_vars) if sum(a) == total],
        dtype=int,
    ).reshape(-1, n_vars)


def exact_moments(alphas):
    """alpha! d! / (|alpha| + d)! for each row of alphas (d = n_vars - 1)."""
    d = alphas.shape[1] - 1
    return np.array(
        [
            math.prod(math.factorial(int(k)) for k in a) * math.factorial(d) / math.factorial(int(a.sum()) + d)
            for a in alphas
        ]
    )


def rule_moments(bary, weights, alphas):
    """sum_i w_i prod_k bary[i, k]^alpha_k for each alpha."""
    return np.prod(bary[None, :, :] ** alphas[:, None, :], axis=2) @ weights


def check_exact_to(bary, weights, degree):
    # On a simplex sum_k lambda_k = 1, so the monomials of total degree exactly p span all
    # polynomials of degree <= p; still check every degree for clearer failures.
    for p in range(degree + 1):
        alphas = multi_indices(bary.shape[1], p)
        np.testing.assert_allclose(
            rule_moments(bary, weights, alphas), exact_moments(alphas), rtol=1e-12, atol=1e-16,
            err_msg=f"degree {p} moments",
        )


def max_moment_error(bary, weights, p):
    alphas = multi_indices(bary.shape[1], p)
    return np.abs(rule_moments(bary, weights, alphas) - exact_moments(alphas)).max()


# ----------------------------------------------------------------------------- reference rules


@pytest.mark.parametrize("degree", range(SEGMENT_MAX_DEGREE + 1))
def test_segment_rule_exact(degree):
    t, w = segment_rule(degree)
    assert t.ndim == 1 and t.shape == w.shape
    assert np.all(w > 0) and np.all((t > 0) & (t < 1))
    assert abs(w.sum() - 1.0) < 1e-14
    k = np.arange(degree + 1)
    np.testing.assert_allclose((t[None, :] ** k[:, None]) @ w, 1.0 / (k + 1), rtol=1e-13)


@pytest.mark.parametrize("degree", [1, 3, 5, 9])
def test_segment_rule_not_exact_beyond(degree):
    # n-point Gauss is exact to 2n - 1 = degree for odd degree, not to degree + 1.
    t, w = segment_rule(degree)
    assert abs(t ** (degree + 1) @ w - 1.0 / (degree + 2)) > 1e-6


@pytest.mark.parametrize(
    "rule, degrees",
    [(triangle_rule, range(TRIANGLE_MAX_DEGREE + 1)), (tetrahedron_rule, range(13))],
)
def test_simplex_rules_exact_positive_interior(rule, degrees):
    for degree in degrees:
        bary, w = rule(degree)
        k = 3 if rule is triangle_rule else 4
        assert bary.shape == (w.size, k)
        assert np.all(w > 0), degree
        assert abs(w.sum() - 1.0) < 1e-14, degree
        assert np.all(bary > 0) and np.all(bary < 1), degree
        np.testing.assert_allclose(bary.sum(axis=1), 1.0, atol=1e-15)
        check_exact_to(bary, w, degree)


def test_tetrahedron_rule_highest_degree():
    bary, w = tetrahedron_rule(TETRAHEDRON_MAX_DEGREE)
    assert np.all(w > 0)
    alphas = multi_indices(4, TETRAHEDRON_MAX_DEGREE)
    np.testing.assert_allclose(rule_moments(bary, w, alphas), exact_moments(alphas), rtol=1e-11)


def test_symmetric_rules_are_small():
    # point counts of the fully symmetric rules (speed on ~1e6 elements)
    assert [triangle_rule(p)[1].size for p in range(9)] == [1, 1, 3, 6, 6, 7, 12, 15, 16]
    assert [tetrahedron_rule(p)[1].size for p in range(7)] == [1, 1, 4, 8, 14, 14, 24]


@pytest.mark.parametrize(
    "rule, degree",
    [(triangle_rule, p) for p in (1, 2, 5, 6, 7, 8)] + [(tetrahedron_rule, p) for p in (1, 2, 3, 5, 6)],
)
def test_rules_fail_one_degree_higher(rule, degree):
    """The moment check is able to fail: these rules are exact to exactly their degree."""
    bary, w = rule(degree)
    assert max_moment_error(bary, w, degree + 1) > 1e-8


def test_symmetric_rule_is_permutation_invariant():
    for rule, k, degrees in ((triangle_rule, 3, range(9)), (tetrahedron_rule, 4, range(7))):
        for degree in degrees:
            bary, w = rule(degree)
            key = {tuple(np.round(b, 12)): wi for b, wi in zip(bary, w)}
            for perm in itertools.permutations(range(k)):
                for b, wi in zip(bary[:, perm], w):
                    assert abs(key[tuple(np.round(b, 12))] - wi) < 1e-14


@pytest.mark.parametrize("rule", [segment_rule, triangle_rule, tetrahedron_rule])
def test_rules_are_read_only(rule):
    pts, w = rule(4)
    w0 = w.copy()
    with pytest.raises(ValueError):
        w[0] = 5.0
    with pytest.raises(ValueError):
        pts[0] = 0.0
    np.testing.assert_array_equal(rule(4)[1], w0)


@pytest.mark.parametrize(
    "rule, maximum",
    [(segment_rule, SEGMENT_MAX_DEGREE), (triangle_rule, TRIANGLE_MAX_DEGREE), (tetrahedron_rule, TETRAHEDRON_MAX_DEGREE)],
)
def test_bad_degree(rule, maximum):
    assert maximum >= 6
    for bad in (-1, maximum + 1):
        with pytest.raises(ValueError, match=f"0..{maximum}"):
            rule(bad)
    for bad in (2.5, "2", None, True):
        with pytest.raises(ValueError, match="degree"):
            rule(bad)
    rule(np.int64(2))  # numpy integers are fine


def test_supported_ranges_meet_contract():
    assert TRIANGLE_MAX_DEGREE >= 8 and TETRAHEDRON_MAX_DEGREE >= 6


# ----------------------------------------------------------------------------- mapped rules

RNG_SEED = 20240611


def random_simplices(n_vertices, m=7, seed=RNG_SEED):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(m, n_vertices, 3)) * rng.uniform(0.1, 3.0, size=(m, 1, 1)) + rng.normal(size=(m, 1, 3))


def second_moment(vertices, measure):
    """int_T x x^T = |T| / ((d+1)(d+2)) (sum x_v x_v^T + (sum x_v)(sum x_v)^T), (m, 3, 3)."""
    d = vertices.shape[1] - 1
    s = vertices.sum(axis=1)
    outer = np.einsum("mvi,mvj->mij", vertices, vertices) + np.einsum("mi,mj->mij", s, s)
    return measure[:, None, None] * outer / ((d + 1) * (d + 2))


def affine_power_integral(vertex_values, measure, p):
    """int_T l^p for affine l with vertex values (m, d+1): |T| p! d!/(p+d)! h_p(l_0..l_d)."""
    d = vertex_values.shape[1] - 1
    alphas = multi_indices(d + 1, p)
    h = np.prod(vertex_values[:, None, :] ** alphas[None, :, :], axis=2).sum(axis=1)
    return measure * math.factorial(p) * math.factorial(d) / math.factorial(p + d) * h


def segment_lengths(v):
    return np.sqrt(((v[:, 1] - v[:, 0]) ** 2).sum(axis=1))


def triangle_areas(v):
    a, b = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    # Lagrange identity |a x b|^2 = |a|^2 |b|^2 - (a.b)^2
    return 0.5 * np.sqrt((a * a).sum(1) * (b * b).sum(1) - (a * b).sum(1) ** 2)


def tet_volumes(v):
    a, b, c = (v[:, k] - v[:, 0] for k in (1, 2, 3))
    triple = (
        a[:, 0] * (b[:, 1] * c[:, 2] - b[:, 2] * c[:, 1])
        - a[:, 1] * (b[:, 0] * c[:, 2] - b[:, 2] * c[:, 0])
        + a[:, 2] * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])
    )
    return np.abs(triple) / 6.0


MAPS = [
    (map_segments, 2, segment_lengths, [0, 1, 2, 3, 5, 8]),
    (map_triangles, 3, triangle_areas, [0, 1, 2, 3, 4, 5, 6, 7, 8, 11]),
    (map_tetrahedra, 4, tet_volumes, [0, 1, 2, 3, 4, 5, 6, 7]),
]


@pytest.mark.parametrize("mapper, nv, exact_measure, degrees", MAPS)
def test_mapped_measure_and_polynomials(mapper, nv, exact_measure, degrees):
    v = random_simplices(nv)
    m = v.shape[0]
    meas = exact_measure(v)
    rng = np.random.default_rng(RNG_SEED + 1)
    a, c = rng.normal(size=3), rng.normal()
    for degree in degrees:
        quad = mapper(v, degree)
        q = quad.n_points
        assert quad.points.shape == (m, q, 3) and quad.weights.shape == (m, q)
        assert quad.n_elements == m and quad.bary.shape == (q, nv)
        np.testing.assert_array_equal(quad.parent, np.arange(m))
        np.testing.assert_allclose(quad.measure, meas, rtol=1e-13)
        # int_T l^degree for an affine l(x) = a.x + c
        l_quad = quad.points @ a + c
        l_vert = v @ a + c
        expected = affine_power_integral(l_vert, meas, degree)
        np.testing.assert_allclose(
            quad.integrate_per_element(l_quad**degree), expected, rtol=1e-11, atol=1e-12 * np.abs(expected).max()
        )
        assert np.isclose(quad.integrate(l_quad**degree), expected.sum(), rtol=1e-11)
        if degree >= 2:
            xx = quad.integrate_per_element(np.einsum("mqi,mqj->mqij", quad.points, quad.points))
            np.testing.assert_allclose(xx, second_moment(v, meas), rtol=1e-12, atol=1e-12)
            total = quad.integrate(np.einsum("mqi,mqj->mqij", quad.points, quad.points))
            assert total.shape == (3, 3)
            np.testing.assert_allclose(total, second_moment(v, meas).sum(0), rtol=1e-12)


def test_map_triangles_normal():
    v = random_simplices(3)
    quad = map_triangles(v, 2)
    n = quad.normal
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, rtol=1e-14)
    for k in (1, 2):
        np.testing.assert_allclose(np.einsum("mi,mi->m", n, v[:, k] - v[:, 0]), 0.0, atol=1e-12)
    # right-hand rule: the unit triangle in the xy-plane has normal +z, reversed order -z
    tri = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    np.testing.assert_allclose(map_triangles(tri, 1).normal, [[0, 0, 1]])
    np.testing.assert_allclose(map_triangles(tri[:, ::-1], 1).normal, [[0, 0, -1]])
    # an explicit normal is rescaled to unit length
    np.testing.assert_allclose(map_triangles(tri, 1, normal=[[0, 0, -4.0]]).normal, [[0, 0, -1]])


def test_map_triangles_of_a_mesh_with_its_areas_and_normals():
    """The nodes and triangles of a mesh with its areas and normals give the same rule as the
    gathered vertices; ``whole`` is kept; missing normal/areas or wrong shapes are errors."""
    from cutfem.geometry.surface_meshes import torus_mesh

    mesh = torus_mesh(12, "perturbed", seed=1)
    ref = map_triangles(mesh.points[mesh.triangles], 4, normal=mesh.normals)
    quad = map_triangles(mesh.points, 4, normal=mesh.normals, areas=mesh.areas, triangles=mesh.triangles, whole=mesh.n_triangles)
    np.testing.assert_array_equal(quad.points, ref.points)
    np.testing.assert_allclose(quad.weights, ref.weights, rtol=1e-14, atol=0)
    assert quad.whole == mesh.n_triangles and ref.whole == 0
    with pytest.raises(ValueError, match="come with normal and areas"):
        map_triangles(mesh.points, 4, triangles=mesh.triangles)
    with pytest.raises(ValueError, match="areas must have shape"):
        map_triangles(mesh.points, 4, normal=mesh.normals, areas=mesh.areas[:-1], triangles=mesh.triangles)
    with pytest.raises(ValueError, match="give normal= with areas="):
        map_triangles(mesh.points[mesh.triangles], 4, areas=mesh.areas)


def test_degenerate_triangle_needs_explicit_normal():
    tri = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0.0, 0, 0], [1, 1, 1], [2, 2, 2]]])
    with pytest.raises(ValueError, match="zero area"):
        map_triangles(tri, 2)
    quad = map_triangles(tri, 2, normal=[[0, 0, 1.0], [1, -1, 0]])
    np.testing.assert_allclose(quad.measure, [0.5, 0.0])
    with pytest.raises(ValueError, match="normal"):
        map_triangles(tri, 2, normal=[[0, 0, 1.0], [0, 0, 0]])
    with pytest.raises(ValueError, match="normal"):
        map_triangles(tri, 2, normal=[[0, 0, 1.0]])


def test_mapped_points_are_bary_combinations():
    v = random_simplices(4, m=3)
    quad = map_tetrahedra(v, 3, parent=[5, 2, 9])
    np.testing.assert_allclose(quad.points[1], quad.bary @ v[1])
    np.testing.assert_array_equal(quad.parent, [5, 2, 9])
    assert quad.normal is None


def test_bad_vertices_and_values():
    with pytest.raises(ValueError, match=r"\(m, 3, 3\)"):
        map_triangles(np.zeros((2, 4, 3)), 2)
    with pytest.raises(ValueError, match=r"\(m, 4, 3\)"):
        map_tetrahedra(np.zeros((4, 3)), 2)
    v = random_simplices(2, m=2)
    v[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        map_segments(v, 2)
    quad = map_segments(random_simplices(2, m=2), 3)
    with pytest.raises(ValueError, match="values"):
        quad.integrate(np.ones((2, quad.n_points + 1)))
    with pytest.raises(ValueError, match="values"):
        quad.integrate_per_element(np.ones(2))
    with pytest.raises(ValueError, match="parent"):
        map_segments(random_simplices(2, m=2), 3, parent=[0, 1, 2])
    with pytest.raises(ValueError, match="parent"):
        map_segments(random_simplices(2, m=2), 3, parent=[0.0, 1.5])
    with pytest.raises(ValueError, match="weights"):
        Quadrature(np.zeros((2, 3, 3)), np.zeros((2, 4)))


def test_integrate_constant_and_trailing_shape():
    # unit square [0,1]^2 split into two triangles; int x dA = (1/2, 1/2, 0)
    tri = np.array([[[0.0, 0, 0], [1, 0, 0], [1, 1, 0]], [[0.0, 0, 0], [1, 1, 0], [0, 1, 0]]])
    quad = map_triangles(tri, 1)
    assert quad.integrate(np.ones((2, quad.n_points))) == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_allclose(quad.integrate(quad.points), [0.5, 0.5, 0.0], atol=1e-15)
    assert quad.integrate_per_element(quad.points).shape == (2, 3)


def test_concatenate():
    t1, t2 = random_simplices(3, m=4, seed=1), random_simplices(3, m=3, seed=2)
    a = map_triangles(t1, 4, parent=np.arange(4))
    b = map_triangles(t2, 4, parent=[10, 11, 12])
    c = concatenate(a, b)
    assert c.n_elements == 7 and c.n_points == a.n_points
    np.testing.assert_array_equal(c.parent, [0, 1, 2, 3, 10, 11, 12])
    np.testing.assert_allclose(c.measure, np.concatenate([triangle_areas(t1), triangle_areas(t2)]), rtol=1e-13)
    assert c.normal.shape == (7, 3)
    np.testing.assert_array_equal(c.bary, a.bary)
    assert concatenate([a, b]).n_elements == 7
    # different points per element
    with pytest.raises(ValueError, match="points per element"):
        concatenate(a, map_triangles(t2, 2))
    # same q (6 points) but a different reference rule: Gauss segment rule of degree 10
    seg = map_segments(random_simplices(2, m=2), 10)
    assert seg.n_points == a.n_points
    with pytest.raises(ValueError, match="normal"):
        concatenate(a, seg)
    seg_with_normal = Quadrature(seg.points, seg.weights, normal=a.normal[:2], bary=seg.bary)
    with pytest.raises(ValueError, match="reference rules"):
        concatenate(a, seg_with_normal)
    with pytest.raises(ValueError):
        concatenate()


def test_mapped_points_gather_and_barycentric_values():
    """mapped_points on gathered vertices and on (nodes, simplices) give the same points, equal to
    bary @ vertices; the P1 basis values at mapped points are the rule's barycentric coordinates."""
    from cutfem.geometry.quadrature import mapped_points, tetrahedron_rule
    from cutfem.geometry.mesh import barycentric_gradients
    from cutfem.fem.spaces import barycentric_at

    rng = np.random.default_rng(5)
    nodes = rng.normal(size=(30, 3))
    tets = np.array([rng.choice(30, 4, replace=False) for _ in range(50)])
    bary, _ = tetrahedron_rule(4)
    ref = np.einsum("qv,mvd->mqd", bary, nodes[tets])
    np.testing.assert_allclose(mapped_points(bary, nodes[tets]), ref, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(mapped_points(bary, nodes, tets), mapped_points(bary, nodes[tets]))
    grads, _ = barycentric_gradients(nodes[tets])
    lam = barycentric_at(ref, nodes[tets[:, 0]], grads)
    np.testing.assert_allclose(lam, np.broadcast_to(bary, lam.shape), atol=1e-9)
    for k in (2, 3):  # segments and triangles: the same sums on their k vertices
        b = rng.random((5, k))
        np.testing.assert_allclose(mapped_points(b, nodes, tets[:, :k]), np.einsum("qv,mvd->mqd", b, nodes[tets[:, :k]]),
                                   rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match=r"bary \(q, 2\)"):
        mapped_points(np.ones((3, 1)), nodes, tets[:, :1])


def test_signed_volumes_triple_product():
    from cutfem.geometry.quadrature import signed_volumes

    rng = np.random.default_rng(5)
    v = rng.normal(size=(2000, 4, 3))
    vol = signed_volumes(v)
    np.testing.assert_allclose(vol, np.linalg.det(v[:, 1:] - v[:, :1]) / 6.0, rtol=1e-10, atol=1e-14)
    # the same bits as the numpy expression of the triple product, term by term
    a, b, c = (v[:, k] - v[:, 0] for k in (1, 2, 3))
    numpy_terms = (a[:, 0] * (b[:, 1] * c[:, 2] - b[:, 2] * c[:, 1]) + a[:, 1] * (b[:, 2] * c[:, 0] - b[:, 0] * c[:, 2])
                   + a[:, 2] * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])) / 6.0
    np.testing.assert_array_equal(vol, numpy_terms)
    np.testing.assert_allclose(signed_volumes(v[:, [1, 0, 2, 3]]), -vol, rtol=1e-10, atol=1e-14)  # orientation flips the sign
    unit = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]])
    assert signed_volumes(unit)[0] == 1 / 6
    with pytest.raises(ValueError, match=r"\(m, 4, 3\)"):
        signed_volumes(v[:, :3])
