"""Tests for cutfem.fem.spaces: P1 data of meshed fields, trace fields on the cut tets and bulk fields on a side.

Expected values come from independent formulas written here: basis gradients by inverting the
vertex systems, Heron's formula, cross products, exact volumes of boxes cut by planes, and the
exactness of P1 for linear functions.
"""

from collections import defaultdict

import numpy as np
import pytest

from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.markers import CUT, NEG, POS
from cutfem.geometry.box import structured_box
from cutfem.fem.spaces import CutSpace, SurfaceP1Space, barycentric_at, triangle_gradients
from cutfem.geometry.surface_meshes import torus_mesh


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def tet_gradients(X):
    """(4, 3) gradients of the barycentric functions of the tet with vertex rows X: rows 1.. of
    the inverse of the matrix with columns (1, x_j)."""
    T = np.vstack([np.ones(4), X.T])
    return np.linalg.inv(T)[:, 1:]


def heron(P):
    a, b, c = (np.linalg.norm(P[i] - P[(i + 1) % 3]) for i in range(3))
    s = 0.5 * (a + b + c)
    return np.sqrt(s * (s - a) * (s - b) * (s - c))


@pytest.fixture(scope="module")
def cut_sphere():
    box = structured_box([-1, -1, -1], [1, 1, 1], cells=10)
    return CutSpace(cut_mesh(box, Sphere(0.7, [0.04, -0.03, 0.02])))


@pytest.fixture(scope="module")
def meshed_torus():
    return SurfaceP1Space(torus_mesh(12, "perturbed-flipped", seed=2))


# ----------------------------------------------------------------------------------------------
# element helpers
# ----------------------------------------------------------------------------------------------


def test_triangle_gradients_normals_areas():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(20, 3, 3))
    grads, normals, areas = triangle_gradients(P)
    for e in range(20):
        E = np.column_stack([P[e, 1] - P[e, 0], P[e, 2] - P[e, 0]])
        G = E @ np.linalg.inv(E.T @ E)  # tangential, with g_a . e_b = delta_ab
        expected = np.array([-G[:, 0] - G[:, 1], G[:, 0], G[:, 1]])
        np.testing.assert_allclose(grads[e], expected, atol=1e-10 * np.abs(expected).max())
        assert areas[e] == pytest.approx(heron(P[e]), rel=1e-9)
        assert np.linalg.norm(normals[e]) == pytest.approx(1.0, abs=1e-14)
        assert abs(normals[e] @ E[:, 0]) < 1e-12 * np.linalg.norm(E) and abs(normals[e] @ E[:, 1]) < 1e-12 * np.linalg.norm(E)
    # right-hand rule orientation
    _, n, _ = triangle_gradients(np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]]))
    np.testing.assert_array_equal(n[0], [0.0, 0.0, 1.0])


def test_barycentric_at_vertices_is_identity():
    rng = np.random.default_rng(1)
    X = rng.normal(size=(5, 4, 3))
    grads = np.array([tet_gradients(x) for x in X])
    lam = barycentric_at(X, X[:, 0], grads)  # points = the vertices themselves
    np.testing.assert_allclose(lam, np.broadcast_to(np.eye(4), (5, 4, 4)), atol=1e-12)
    P = rng.normal(size=(5, 3, 3))
    g, _, _ = triangle_gradients(P)
    np.testing.assert_allclose(barycentric_at(P, P[:, 0], g), np.broadcast_to(np.eye(3), (5, 3, 3)), atol=1e-12)


# ----------------------------------------------------------------------------------------------
# SurfaceP1Space
# ----------------------------------------------------------------------------------------------


def test_surface_space_data(meshed_torus):
    V = meshed_torus
    mesh = V.mesh
    N = 12 * 6
    assert V.n_dofs == N and V.n_elements == 2 * N
    assert V.h == pytest.approx(N**-0.5, rel=1e-15)
    assert SurfaceP1Space(mesh, h=0.3).h == 0.3
    np.testing.assert_array_equal(V.element_dofs, mesh.triangles)
    # quadrature on S_h: weights sum to the area, points inside the triangles
    area = sum(heron(np.asarray(mesh.points)[t]) for t in mesh.triangles)
    for degree in (0, 2, 4):
        q = mesh.ds().quadrature(degree)
        assert q.weights.sum() == pytest.approx(area, rel=1e-12)
    # a field on a surface mesh does not live on the tets of a cut
    cut = cut_mesh(structured_box([-2, -2, -1], [2, 2, 1], cells=4), Sphere(0.9))
    with pytest.raises(ValueError, match="does not live on the measure"):
        V.evaluate(np.zeros(V.n_dofs), cut.dx(CUT))


def test_surface_space_edges(meshed_torus):
    V = meshed_torus
    pairs, conormals, lengths = V.edges()
    pts, tris = np.asarray(V.dof_points), V.element_dofs
    assert len(pairs) == 3 * V.n_elements // 2
    for e in range(len(pairs)):
        common = np.intersect1d(tris[pairs[e, 0]], tris[pairs[e, 1]])
        assert len(common) == 2
        d = pts[common[1]] - pts[common[0]]
        assert lengths[e] == pytest.approx(np.linalg.norm(d), rel=1e-14)
        for s in range(2):
            t = conormals[e, s]
            tri = tris[pairs[e, s]]
            opposite = pts[np.setdiff1d(tri, common)[0]]
            assert np.linalg.norm(t) == pytest.approx(1.0, abs=1e-13)
            assert abs(t @ d) < 1e-12 and abs(t @ V.element_normals[pairs[e, s]]) < 1e-12
            assert t @ (opposite - pts[common[0]]) < 0  # points out of the triangle


# ----------------------------------------------------------------------------------------------
# CutSpace
# ----------------------------------------------------------------------------------------------


def test_cut_space_data(cut_sphere):
    V = cut_sphere
    cut = V.cut
    assert V.h == pytest.approx(11**-1.0, rel=1e-14)  # N = 11^3 background nodes
    assert CutSpace(cut, h=0.5).h == 0.5
    assert V.n_dofs == len(V.dof_points) == len(V.node_ids) and V.n_elements == len(V.element_dofs)
    np.testing.assert_allclose(V.dof_points, np.asarray(cut.background.points)[V.node_ids], atol=0)
    for k in range(V.n_elements):
        X = V.dof_points[V.element_dofs[k]]
        expected = tet_gradients(X)
        np.testing.assert_allclose(V.element_gradients[k], expected, atol=1e-11 * np.abs(expected).max())
        assert V.element_volumes[k] == pytest.approx(abs(np.linalg.det(X[1:] - X[0])) / 6, rel=1e-12)
    # piece normals are unit and orthogonal to the piece triangles
    tri_pts = cut.vertices[cut.triangles]
    n = V.element_normals[cut.triangle_tets]
    np.testing.assert_allclose(np.linalg.norm(V.element_normals, axis=1), 1.0, atol=1e-14)
    for a, b in ((0, 1), (0, 2)):
        assert np.abs(np.einsum("ij,ij->i", tri_pts[:, b] - tri_pts[:, a], n)).max() < 1e-12
    # the measure of the whole cut tets is their union
    q = cut.dx(CUT).quadrature(2)
    assert q.weights.sum() == pytest.approx(V.n_elements * (0.2**3 / 6), rel=1e-12)  # Kuhn tets: 1/6 of a cube
    # the trace field does not live on the tets inside the surface
    with pytest.raises(ValueError, match="not in the element set"):
        V.evaluate(np.zeros(V.n_dofs), cut.dx(NEG))


def test_cut_space_faces(cut_sphere):
    V = cut_sphere
    facets = V.cut.interior_facets(CUT)
    assert facets.elements is V.elements
    pairs, normals, areas = facets.pairs, facets.normals, facets.areas
    assert facets.n_facets == len(pairs)
    tets, pts = V.element_dofs, V.dof_points
    # the same faces as an independent count of faces shared by two active tets
    owners = defaultdict(list)
    for k, T in enumerate(tets):
        for a in range(4):
            owners[tuple(sorted(np.delete(T, a).tolist()))].append(k)
    shared = {f: ks for f, ks in owners.items() if len(ks) == 2}
    assert len(pairs) == len(shared)
    got = {tuple(sorted(np.intersect1d(tets[p[0]], tets[p[1]]).tolist())) for p in pairs}
    assert got == set(shared)
    for f in range(len(pairs)):
        common = np.intersect1d(tets[pairs[f, 0]], tets[pairs[f, 1]])
        X = pts[common]
        cross = np.cross(X[1] - X[0], X[2] - X[0])
        assert areas[f] == pytest.approx(0.5 * np.linalg.norm(cross), rel=1e-12)
        assert np.linalg.norm(normals[f]) == pytest.approx(1.0, abs=1e-13)
        assert abs(normals[f] @ unit(cross)) == pytest.approx(1.0, abs=1e-12)
        opposite = pts[np.setdiff1d(tets[pairs[f, 0]], common)[0]]
        assert normals[f] @ (opposite - X[0]) < 0  # out of the first tet
        for s in range(2):  # the local vertex opposite to the face, in each tet
            assert tets[pairs[f, s], facets.opposite[f, s]] not in common
        # the face's vertices and size h_F, the longest edge
        np.testing.assert_array_equal(np.sort(facets.vertices[f], axis=0), np.sort(X, axis=0))
        longest = max(np.linalg.norm(X[a] - X[b]) for a, b in ((0, 1), (1, 2), (0, 2)))
        assert facets.h[f] == pytest.approx(longest, rel=1e-14)


def test_cut_space_edges(cut_sphere):
    V = cut_sphere
    cut = V.cut
    pairs, conormals, lengths = V.edges()
    # a closed polyhedral S_h: every polygon edge is shared by two pieces.  Count polygon edges
    # independently: edges of the triangles of a piece that appear once in that piece.
    per_piece = defaultdict(lambda: defaultdict(int))
    for tri, k in zip(cut.triangles, cut.triangle_tets):
        for a in range(3):
            per_piece[k][tuple(sorted((tri[a], tri[(a + 1) % 3])))] += 1
    polygon_edges = sum(1 for c in per_piece.values() for m in c.values() if m == 1)
    assert 2 * len(pairs) == polygon_edges
    e = cut.surface_edges
    d = cut.vertices[e[:, 1]] - cut.vertices[e[:, 0]]
    np.testing.assert_allclose(lengths, np.linalg.norm(d, axis=1), rtol=1e-14)
    for s in range(2):
        t = conormals[:, s]
        k = pairs[:, s]
        np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1.0, atol=1e-13)
        assert np.abs(np.einsum("ij,ij->i", t, d)).max() < 1e-12
        assert np.abs(np.einsum("ij,ij->i", t, V.element_normals[k])).max() < 1e-12
        # out of the piece: away from the mean of the piece's vertices
        cent = np.array([cut.vertices[np.unique(cut.triangles[cut.triangle_tets == kk])].mean(axis=0) for kk in k])
        mid = 0.5 * (cut.vertices[e[:, 0]] + cut.vertices[e[:, 1]])
        assert np.all(np.einsum("ij,ij->i", t, mid - cent) > 0)


# ----------------------------------------------------------------------------------------------
# evaluation of discrete functions
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("which", ["meshed", "cut"])
def test_linear_functions_are_reproduced(which, meshed_torus, cut_sphere):
    V = meshed_torus if which == "meshed" else cut_sphere
    g, c = np.array([0.3, -1.2, 0.7]), 0.25
    u = V.interpolate(lambda x: x @ g + c)
    assert u.shape == (V.n_dofs,)
    ds = V.mesh.ds() if which == "meshed" else V.cut.ds()
    q = ds.quadrature(4)
    np.testing.assert_allclose(V.evaluate(u, ds, 4), q.points @ g + c, atol=1e-12)
    X = V.interpolate(lambda x: x)  # vector-valued: the coordinate map
    assert X.shape == (V.n_dofs, 3)
    np.testing.assert_allclose(V.evaluate(X, ds, 4), q.points, atol=1e-12)
    phi = V.basis_at(q.points, q.parent)
    np.testing.assert_allclose(phi.sum(axis=2), 1.0, atol=1e-12)
    points, triangles, values = V.surface_vertex_data(u)  # the trace at the vertices of S_h
    assert values.shape == (len(points),) and triangles.max() == len(points) - 1
    np.testing.assert_allclose(values, points @ g + c, atol=1e-12)
    np.testing.assert_allclose(V.surface_vertex_data(X)[2], points, atol=1e-12)
    with pytest.raises(ValueError, match="shape"):
        V.surface_vertex_data(u[:-1])
    grad = V.element_gradient_of(u)
    gradX = V.element_gradient_of(X)  # (n_el, 3, 3): row c is the gradient of x_c
    if which == "cut":  # full 3-d gradients on the tets
        np.testing.assert_allclose(grad, np.broadcast_to(g, grad.shape), atol=1e-11)
        np.testing.assert_allclose(gradX, np.broadcast_to(np.eye(3), gradX.shape), atol=1e-11)
    else:  # surface gradients: P_K g and P_K
        n = V.element_normals
        P = np.eye(3) - n[:, :, None] * n[:, None, :]
        np.testing.assert_allclose(grad, P @ g, atol=1e-11)
        np.testing.assert_allclose(gradX, P, atol=1e-11)


# ----------------------------------------------------------------------------------------------
# bulk fields: CutSpace(cut, NEG) with the measure cut.dx(NEG)
# ----------------------------------------------------------------------------------------------


def test_cut_volume_space_plane():
    """phi = z - 0.1 on [-1, 1]^3 with spacing 0.5: the region is the slab z < 0.1 (volume 4.4),
    the elements are the tets with a node at z <= 0 (three layers of cells, volume 6)."""
    box = structured_box([-1, -1, -1], [1, 1, 1], spacing=0.5)
    cut = cut_mesh(box, lambda x: x[..., 2] - 0.1, check_boundary=False)  # a slab meets the box sides
    V = CutSpace(cut, NEG)
    dx = cut.dx(NEG)
    tets = np.asarray(box.tets)
    expected = np.flatnonzero((box.points[tets][:, :, 2] < 0.1).any(axis=1))
    np.testing.assert_array_equal(np.sort(V.elements.tet_ids), expected)
    assert len(V.element_dofs) == 3 * 16 * 6
    assert V.n_dofs == 5 * 5 * 4  # node layers z = -1, -0.5, 0, 0.5
    assert V.h == pytest.approx(125 ** (-1 / 3), rel=1e-14)
    q = dx.quadrature(2)
    assert q.weights.sum() == pytest.approx(4 * 1.1, rel=1e-13)
    # int z over [-1,1]^2 x [-1, 0.1] = 4 (0.1^2 - 1) / 2
    assert np.sum(q.weights * q.points[..., 2]) == pytest.approx(2 * (0.01 - 1), rel=1e-12)
    # the quadrature parents are the elements holding the points
    lam = V.basis_at(q.points, V.local_elements(dx, q.parent))
    assert lam.min() > -1e-12 and lam.max() < 1 + 1e-12
    assert cut.dx(V.elements).quadrature(1).weights.sum() == pytest.approx(6.0, rel=1e-13)
    # the field on NEG does not live on the tets above the slab
    with pytest.raises(ValueError, match="not in the element set"):
        V.evaluate(np.zeros(V.n_dofs), cut.dx(POS))


def test_cut_volume_space_sphere_volume_converges():
    """|{phi_h < 0}| -> 4/3 pi R^3 at O(h^2) (a polyhedron inscribed in the ball up to O(h^2))."""
    R = 0.7
    errors = []
    for cells in (8, 16):
        cut = cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=cells), Sphere(R, [0.01, 0.02, -0.03]))
        errors.append(abs(cut.dx(NEG).quadrature(1).weights.sum() - 4 / 3 * np.pi * R**3))
    assert errors[1] < errors[0] / 3  # rate >= log2(3) ~ 1.6, expected 2


def test_locate_set_keeps_one_search_and_checks_the_rows_asked():
    """ElementSet.locate_set: the local indices of another set's tets, equal to locate; a second
    call reuses the search; only the rows asked must lie in the set (a side's cut tets lie in the
    other side's set, its whole tets do not)."""
    cut = cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), Sphere(0.6))
    neg, pos, cutset = cut.elements(NEG), cut.elements(POS), cut.elements(CUT)
    np.testing.assert_array_equal(neg.locate_set(cutset), neg.locate(cutset.tet_ids))
    assert neg._positions[id(cutset)][0] is cutset and len(neg._positions) == 1
    rows = np.array([5, 0, 3])
    np.testing.assert_array_equal(neg.locate_set(cutset, rows), neg.locate(cutset.tet_ids[rows]))
    assert len(neg._positions) == 1
    in_both = np.flatnonzero(neg.contains(pos.tet_ids))
    assert 0 < len(in_both) < pos.n_elements
    np.testing.assert_array_equal(neg.locate_set(pos, in_both), neg.locate(pos.tet_ids[in_both]))
    with pytest.raises(ValueError, match="not in the element set 'neg'"):
        neg.locate_set(pos)


def test_a_field_outside_its_elements_names_the_distinct_tets_missing():
    """The error of a measure outside a field's elements counts the measure's background tets, not
    the quadrature cells of the block that asked (a cut tet's part of a side is several sub-tets):
    a field inside the sphere of radius 0.5 integrated over the inside of a larger sphere's cut on
    the same box; whichever term asks, the count is the number of tets of that measure that are not
    in the field's set."""
    box = structured_box([-1, -1, -1], [1, 1, 1], cells=6)
    V = CutSpace(cut_mesh(box, Sphere(0.5)), NEG)
    dx = cut_mesh(box, Sphere(0.9)).dx(NEG)
    expected = int(np.count_nonzero(~V.elements.contains(dx.elements.tet_ids)))
    tets = dx.elements.tet_ids[dx.quadrature(2).parent]  # the background tet of each cell
    outside = tets[~V.elements.contains(tets)]
    assert 0 < expected == len(np.unique(outside)) < len(outside)  # the missing tets repeat among the cells
    for call in (lambda: V.evaluate(np.zeros(V.n_dofs), dx), lambda: V.local_elements(dx)):
        with pytest.raises(ValueError, match=rf"^{expected} elements \(background tets \d+, \d+, \d+, \.\.\.\) of"):
            call()
