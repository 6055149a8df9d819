"""Bulk fields of a cut: sides, measures, restricted and product P1 spaces, forms over measures
(docs/math.md §7-§9).

Every assembled matrix is compared with a reference assembled here element by element (Python
loops over the tets of a small mesh, with basis functions from a 4 x 4 solve per tet, side parts
clipped by hand and split by scipy's convex hull, and quadrature rules written out in this file),
never with numbers produced by the code under test.
"""

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
from scipy.spatial import ConvexHull

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.forms import assemble, bilinear_form
from cutfem.fem.pointwise import dot, jump
from cutfem.fem.terms import (
    face_jump_penalty,
    interface_nitsche,
    load,
    mass,
    nitsche,
    normal_gradient_penalty,
    stiffness,
    tangential_stiffness,
)
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.markers import CUT, NEG, POS
from cutfem.geometry.box import structured_box
from cutfem.geometry.mesh import TetMesh
from cutfem.fem.spaces import CutSpace, ProductSpace

# a sphere in general position: no nodal value is zero, no two values of a tet coincide
CENTRE = (0.031, -0.017, 0.023)
RADIUS = 0.62


def _generic_cut(cells=6):
    box = structured_box([-1, -1, -1], [1, 1, 1], cells=cells)
    phi = Sphere(RADIUS, center=CENTRE)
    return box, phi, cut_mesh(box, phi)


@pytest.fixture(scope="module")
def generic():
    box, phi, cut = _generic_cut()
    values = np.linalg.norm(box.points - np.array(CENTRE), axis=1) - RADIUS  # phi at the nodes, computed here
    return box, cut, values


def _plane_cut(cells=4):
    """phi = z on [-1, 1]^3: the zero set is the node layer z = 0 (a plain callable level set)."""
    box = structured_box([-1, -1, -1], [1, 1, 1], cells=cells)
    return box, cut_mesh(box, lambda x: x[..., 2], check_boundary=False)


# ---------------------------------------------------------------------------------------------
# reference machinery (loops over elements are fine here: the meshes are small)
# ---------------------------------------------------------------------------------------------


def _barycentric(X):
    """(Ainv (4, 4), gradients (4, 3)) of the tet X (4, 3): lambda(p) = Ainv @ (p, 1)."""
    A = np.vstack([X.T, np.ones(4)])
    Ainv = np.linalg.inv(A)
    return Ainv, Ainv[:, :3]


def _lam(Ainv, p):
    """Barycentric coordinates at points p (k, 3): (k, 4)."""
    p = np.atleast_2d(p)
    return (Ainv @ np.vstack([p.T, np.ones(len(p))])).T


def _tet_volume(Y):
    return abs(np.linalg.det(np.stack([Y[1] - Y[0], Y[2] - Y[0], Y[3] - Y[0]]))) / 6.0


def _side_polytope(X, v, side):
    """The points spanning {phi_h on the side} ∩ T (nodes on the side and the edge crossings), or
    None when T has no part there; (X, True) when all of T lies on the side."""
    inside = v < 0 if side == NEG else v > 0
    if not inside.any():
        return None, False
    if inside.all():
        return X, True
    pts = [X[i] for i in range(4) if inside[i]]
    for i in range(4):
        for j in range(i + 1, 4):
            if (v[i] < 0) != (v[j] < 0):
                t = v[i] / (v[i] - v[j])
                pts.append(X[i] + t * (X[j] - X[i]))
    return np.array(pts), False


def _hull_tets(P):
    """The convex polytope spanned by P split into tets from its centroid to its hull triangles."""
    hull = ConvexHull(P)
    c = P[hull.vertices].mean(axis=0)
    return [np.vstack([c, P[s]]) for s in hull.simplices]


def _local_mass(Ainv, Y):
    """int_K lambda_a lambda_b over the tet K with vertices Y: |K|/20 (Phi^T Phi + Phi^T 1 1^T Phi)."""
    Phi = _lam(Ainv, Y)  # (4 vertices, 4 basis)
    s = Phi.sum(axis=0)
    return _tet_volume(Y) / 20.0 * (Phi.T @ Phi + np.outer(s, s))


def _dof_map(space):
    """Background node id -> dof of the field (-1 where the field has none)."""
    box = space.cut.background
    m = -np.ones(box.n_points, dtype=np.int64)
    m[space.node_ids] = np.arange(space.n_dofs)
    return m


def _conical_rule(n):
    """A Stroud conical product rule on the reference tet (Gauss-Legendre in each collapsed
    direction), exact for polynomials of degree <= 2 n - 3: (points (q, 3), weights (q,))."""
    g, w = np.polynomial.legendre.leggauss(n)
    g, w = 0.5 * (g + 1.0), 0.5 * w
    pts, wts = [], []
    for a, wa in zip(g, w):
        for b, wb in zip(g, w):
            for c, wc in zip(g, w):
                pts.append([a, b * (1 - a), c * (1 - a) * (1 - b)])
                wts.append(wa * wb * wc * (1 - a) ** 2 * (1 - b))
    return np.array(pts), np.array(wts)


_MIDPOINTS = np.array([[0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [0.5, 0.0, 0.5]])  # degree-2 triangle rule, weights 1/3


def _triangle_points(T):
    return _MIDPOINTS @ T, np.full(3, 1.0 / 3.0) * 0.5 * np.linalg.norm(np.cross(T[1] - T[0], T[2] - T[0]))


def _reference_bulk(box, values, space, side, kind, f=None):
    """Reference stiffness / mass matrix or load vector of ``space`` over the side's part of every
    tet: whole tets in one batch, the cut tets one by one (clipped here, split by a convex hull)."""
    dof = _dof_map(space)
    n = space.n_dofs
    out = np.zeros(n) if kind == "load" else np.zeros((n, n))
    ref_pts, ref_w = _conical_rule(5)
    inside = values[box.tets] < 0 if side == NEG else values[box.tets] > 0
    X = box.points[box.tets]  # (m, 4, 3)
    Ainv = np.linalg.inv(np.concatenate([X.transpose(0, 2, 1), np.ones((len(X), 1, 4))], axis=1))
    vol = np.abs(np.linalg.det(X[:, 1:] - X[:, :1])) / 6.0
    d = dof[box.tets]
    whole = np.flatnonzero(inside.all(axis=1))
    assert np.all(d[inside.any(axis=1)] >= 0), "a tet with a part on the side lacks dofs of the field"
    if kind == "stiffness":
        G = Ainv[whole, :, :3]
        local = vol[whole, None, None] * G @ G.transpose(0, 2, 1)
    elif kind == "mass":
        local = vol[whole, None, None] / 20.0 * (np.eye(4) + np.ones((4, 4)))
    else:
        x = X[whole, :1] + ref_pts @ (X[whole, 1:] - X[whole, :1])  # (w, q, 3)
        lam = np.einsum("wab,wqb->wqa", Ainv[whole], np.concatenate([x, np.ones(x.shape[:2] + (1,))], axis=2))
        local = np.einsum("wq,wqa->wa", 6.0 * vol[whole, None] * ref_w * f(x), lam)
    if kind == "load":
        np.add.at(out, d[whole], local)
    else:
        np.add.at(out, (d[whole][:, :, None], d[whole][:, None, :]), local)
    for t in np.flatnonzero(inside.any(axis=1) & ~inside.all(axis=1)):  # the cut tets
        P, _ = _side_polytope(X[t], values[box.tets[t]], side)
        dt = d[t]
        for Y in _hull_tets(P):
            if kind == "stiffness":
                G = Ainv[t, :, :3]
                out[np.ix_(dt, dt)] += _tet_volume(Y) * G @ G.T
            elif kind == "mass":
                out[np.ix_(dt, dt)] += _local_mass(Ainv[t], Y)
            else:
                x = Y[0] + ref_pts @ (Y[1:] - Y[0])
                out[dt] += (6.0 * _tet_volume(Y) * ref_w * f(x)) @ _lam(Ainv[t], x)
    return out


def _surface_triangles(cut, values):
    """(background tet, triangle vertices (3, 3), unit normal grad phi_h/|grad phi_h|, h_T) per triangle of S_h."""
    box = cut.background
    for T, tri in zip(cut.triangle_tets, cut.triangle_points):
        t = cut.tet_ids[T]
        nodes = box.tets[t]
        X = box.points[nodes]
        _, G = _barycentric(X)
        g = values[nodes] @ G
        h = max(np.linalg.norm(X[i] - X[j]) for i in range(4) for j in range(i + 1, 4))
        yield t, nodes, X, tri, g / np.linalg.norm(g), h


def _interior_faces(box, tets):
    """{sorted face nodes: [(tet, opposite local vertex), ...]} over background tets ``tets``."""
    faces = {}
    for t in tets:
        nodes = box.tets[t]
        for k in range(4):
            key = tuple(sorted(np.delete(nodes, k)))
            faces.setdefault(key, []).append((t, k))
    return {k: v for k, v in faces.items() if len(v) == 2}


def _reference_face_penalty(box, faces, space, h_power):
    """sum_F h_F^a |F| [n_F . grad u][n_F . grad v] with normals and areas computed here."""
    dof = _dof_map(space)
    K = np.zeros((space.n_dofs, space.n_dofs))
    for key, ((t1, k1), (t2, _)) in faces.items():
        A, B, C = box.points[list(key)]
        c = np.cross(B - A, C - A)
        area = 0.5 * np.linalg.norm(c)
        n = c / np.linalg.norm(c)
        if np.dot(box.points[box.tets[t1][k1]] - A, n) > 0:  # point out of t1
            n = -n
        hF = max(np.linalg.norm(B - A), np.linalg.norm(C - B), np.linalg.norm(A - C))
        d = np.concatenate([dof[box.tets[t1]], dof[box.tets[t2]]])
        G1 = _barycentric(box.points[box.tets[t1]])[1]
        G2 = _barycentric(box.points[box.tets[t2]])[1]
        j = np.concatenate([G1 @ n, -(G2 @ n)])
        np.add.at(K, (d[:, None], d[None, :]), hF**h_power * area * np.outer(j, j))
    return K


def _close(A, B, rtol=1e-12):
    A = A.toarray() if sp.issparse(A) else np.asarray(A)
    B = B.toarray() if sp.issparse(B) else np.asarray(B)
    assert A.shape == B.shape
    scale = max(np.max(np.abs(B)), 1e-300)
    err = np.max(np.abs(A - B)) if A.size else 0.0
    assert err <= rtol * scale, f"max difference {err:.3e} vs scale {scale:.3e}"


def _exactly_symmetric(K):
    K = sp.csr_matrix(K)
    assert abs(K - K.T).max() == 0.0


# ---------------------------------------------------------------------------------------------
# 1. the sides partition the box and every tet
# ---------------------------------------------------------------------------------------------


def _assert_partition(cut):
    box = cut.background
    total = np.zeros(box.n_tets)
    for side in (NEG, POS):
        np.add.at(total, cut.elements(side).tet_ids, cut.dx(side).part_volumes)
    assert np.max(np.abs(total - box.volumes)) <= 1e-12 * box.volumes.max()
    box_volume = float(np.prod(box.upper - box.lower))
    assert abs(cut.dx(NEG).size + cut.dx(POS).size - box_volume) <= 1e-12 * box_volume


def test_sides_partition_every_tet_generic_sphere(generic):
    _, cut, _ = generic
    assert not np.any(cut.background_values == 0.0)
    _assert_partition(cut)


def test_sides_partition_every_tet_with_zeros_at_nodes():
    # centred on a node, radius three cells: nodes (3,0,0), (2,2,1), ... lie exactly on the sphere
    box = structured_box([-1, -1, -1], [1, 1, 1], cells=10)
    cut = cut_mesh(box, Sphere(0.6))
    assert np.sum(cut.background_values == 0.0) >= 30
    _assert_partition(cut)
    es = cut.elements(NEG)  # a structured box: one volume for every tet, and the arrays agree with it
    assert es.uniform_volume == box.tet_volume
    np.testing.assert_allclose(box.volumes[es.tet_ids], es.uniform_volume, rtol=1e-13)
    assert np.all(es.volumes_of(np.arange(5)) == es.uniform_volume) and es.volumes_of(np.arange(5)).shape == (5,)
    assert es.volumes_of(3).shape == () and es.volumes_of(es.tet_ids >= 0).shape == (es.n_elements,)
    with pytest.raises(IndexError):
        es.volumes_of(np.array([es.n_elements]))
    plain = cut_mesh(TetMesh(box.points, box.tets), Sphere(0.6)).elements(NEG)  # a mesh keeps each tet's volume
    assert plain.uniform_volume is None
    np.testing.assert_allclose(plain.volumes, box.tet_volume, rtol=1e-13)


def test_plane_through_nodes_halves_the_box():
    box, cut = _plane_cut()
    assert np.sum(cut.background_values == 0.0) == 25
    _assert_partition(cut)
    assert cut.dx(NEG).size == pytest.approx(4.0, rel=1e-14)
    assert cut.dx(POS).size == pytest.approx(4.0, rel=1e-14)
    assert cut.area == pytest.approx(4.0, rel=1e-14)
    # the NEG set is exactly the tets below the plane; POS the tets above plus the cut tets
    below = np.flatnonzero(box.points[box.tets][:, :, 2].mean(axis=1) < 0)
    assert np.array_equal(np.sort(cut.elements(NEG).tet_ids), below)
    assert cut.elements(POS).n_elements == box.n_tets - below.size + cut.elements(CUT).n_elements


def test_ball_volume_converges_at_second_order():
    exact = 4.0 / 3.0 * np.pi * 0.7**3
    errors = []
    for cells in (8, 16, 32):
        box = structured_box([-1, -1, -1], [1, 1, 1], cells=cells)
        cut = cut_mesh(box, Sphere(0.7, center=(0.013, -0.021, 0.017)))
        errors.append(abs(cut.dx(NEG).size - exact))
    rates = np.log(np.array(errors[:-1]) / errors[1:]) / np.log(2.0)
    assert errors[-1] < 5e-3 * exact
    assert np.all(rates >= 1.8), rates


# ---------------------------------------------------------------------------------------------
# 2. the interface is seen alike from both sides
# ---------------------------------------------------------------------------------------------


def test_interface_measure_is_the_same_from_both_sides(generic):
    _, cut, _ = generic
    for on in (NEG, POS, CUT):
        total = assemble(mass(cut.ds()), CutSpace(cut, on)).sum()
        assert total == pytest.approx(cut.area, rel=1e-12)
    # and the area of S_h is that of its triangles, computed here
    tri = cut.triangle_points
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    assert cut.area == pytest.approx(area, rel=1e-12)


# ---------------------------------------------------------------------------------------------
# 3. jumps across Gamma
# ---------------------------------------------------------------------------------------------


@bilinear_form(symmetric=True)
def _jump_product(u, v, w):
    return (u[0] - u[1]) * (v[0] - v[1])


def test_continuous_function_has_no_jump(generic):
    box, cut, _ = generic
    VN, VP = CutSpace(cut, NEG), CutSpace(cut, POS)
    W = ProductSpace(VN, VP)
    K = assemble(_jump_product * cut.ds(), W)
    rng = np.random.default_rng(1)
    g = rng.normal(size=box.n_points)  # nodal values of a global P1 function
    x = W.join([g[VN.node_ids], g[VP.node_ids]])
    scale = abs(K) @ np.abs(x)
    assert np.max(np.abs(K @ x)) <= 1e-12 * np.max(scale)
    assert abs(x @ K @ x) <= 1e-12 * (np.abs(x) @ scale)
    # a jump of one everywhere: (1, 1)_Gamma = |Gamma_h|
    y = W.join([g[VN.node_ids], g[VP.node_ids] + 1.0])
    assert y @ K @ y == pytest.approx(cut.area, rel=1e-12)
    # a jump of one hat function phi_i: (phi_i, phi_i)_Gamma, the diagonal of the surface mass
    MP = assemble(mass(cut.ds()), VP).diagonal()
    i = int(np.argmax(MP))
    z = x.copy()
    z[W.offsets[1] + i] += 1.0
    assert z @ K @ z == pytest.approx(MP[i], rel=1e-10)
    assert MP[i] > 0.1 * cut.area / cut.n_nodes


# ---------------------------------------------------------------------------------------------
# 4. an interface on grid faces gives standard FEM on the fitted sub-mesh
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("side", [NEG, POS])
def test_fitted_plane_gives_standard_fem(side):
    box, cut = _plane_cut()
    V = CutSpace(cut, side)
    dof = _dof_map(V)
    centroid_z = box.points[box.tets][:, :, 2].mean(axis=1)
    tets = np.flatnonzero(centroid_z < 0 if side == NEG else centroid_z > 0)
    Kref = np.zeros((V.n_dofs, V.n_dofs))
    Mref = np.zeros((V.n_dofs, V.n_dofs))
    for t in tets:
        X = box.points[box.tets[t]]
        d = dof[box.tets[t]]
        assert np.all(d >= 0)
        vol = _tet_volume(X)
        G = _barycentric(X)[1]
        Kref[np.ix_(d, d)] += vol * G @ G.T
        Mref[np.ix_(d, d)] += vol / 20.0 * (np.eye(4) + np.ones((4, 4)))
    _close(assemble(stiffness(cut.dx(side)), V), Kref)
    _close(assemble(mass(cut.dx(side)), V), Mref)


# ---------------------------------------------------------------------------------------------
# 5. the ghost penalty sees only the nonlinear part
# ---------------------------------------------------------------------------------------------


def test_ghost_penalty_vanishes_on_linear_functions(generic):
    _, cut, _ = generic
    V = CutSpace(cut, NEG)
    K = assemble(face_jump_penalty(cut.dF(cut.ghost_facets(NEG)), h_power=1), V)
    x = V.dof_points
    norm = abs(K).sum(axis=1).max()
    for p in (np.ones(V.n_dofs), x[:, 0], x[:, 1], x[:, 2], 2 * x[:, 0] - x[:, 1] + 0.5 * x[:, 2] + 3):
        assert np.max(np.abs(K @ p)) <= 1e-12 * norm * np.max(np.abs(p))
    q = x[:, 0] ** 2 + x[:, 1] * x[:, 2]
    assert q @ K @ q > 1e-3 * norm * np.mean(q**2)


# ---------------------------------------------------------------------------------------------
# 6. every assembled block against a reference assembly
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("side", [NEG, POS])
def test_stiffness_and_mass_on_a_side_match_reference(generic, side):
    box, cut, values = generic
    V = CutSpace(cut, side)
    K = assemble(stiffness(cut.dx(side)), V)
    M = assemble(mass(cut.dx(side)), V)
    _close(K, _reference_bulk(box, values, V, side, "stiffness"))
    _close(M, _reference_bulk(box, values, V, side, "mass"))
    _exactly_symmetric(K)
    _exactly_symmetric(M)


def test_stiffness_in_blocks_of_elements_matches_reference(generic, monkeypatch):
    """The stiffness Gram rows built and multiplied a block of elements at a time (blocks of 7
    elements here) give the reference matrix, exactly symmetric."""
    import cutfem.fem.assembly as assembly

    box, cut, values = generic
    monkeypatch.setattr(assembly, "GRAM_ROWS", 21)
    for side in (NEG, POS):
        V = CutSpace(cut, side)
        K = assemble(stiffness(cut.dx(side)), V)
        _close(K, _reference_bulk(box, values, V, side, "stiffness"))
        _exactly_symmetric(K)


def test_load_on_a_side_matches_an_independent_quadrature(generic):
    box, cut, values = generic
    V = CutSpace(cut, NEG)

    def f(x):  # degree 3: f v is integrated exactly by both rules
        return 1.0 + x[..., 0] - 2.0 * x[..., 1] * x[..., 2] + x[..., 0] ** 3

    b = assemble(load(f, cut.dx(NEG)), V)
    _close(b, _reference_bulk(box, values, V, NEG, "load", f))
    # the load of 1 integrates the basis functions: their sum is the volume of the side
    assert assemble(load(lambda x: np.ones(x.shape[:-1]), cut.dx(NEG)), V).sum() == pytest.approx(cut.dx(NEG).size, rel=1e-12)


def test_nitsche_matches_reference(generic):
    box, cut, values = generic
    V = CutSpace(cut, NEG)
    gamma = 10.0
    dof = _dof_map(V)
    ref = np.zeros((V.n_dofs, V.n_dofs))
    for t, nodes, X, tri, n, h in _surface_triangles(cut, values):
        Ainv, G = _barycentric(X)
        pts, w = _triangle_points(tri)
        lam = _lam(Ainv, pts)  # (3, 4)
        dn = G @ n  # (4,)
        local = np.zeros((4, 4))
        for q in range(3):
            phi = lam[q]
            local += w[q] * (-np.outer(phi, dn) - np.outer(dn, phi) + gamma / h * np.outer(phi, phi))
        d = dof[nodes]
        ref[np.ix_(d, d)] += local
    K = assemble(nitsche(cut.ds(), gamma), V)
    _close(K, ref)
    _exactly_symmetric(K)


@pytest.mark.parametrize("structured", [True, False], ids=["kuhn", "tetmesh"])
def test_nitsche_closed_form_equals_the_quadrature_integrand(structured):
    """The built-in Nitsche matrix (piece moments, lattice-edge or COO sums) against the same terms
    written as an integrand and assembled by degree-2 quadrature on the triangles of Gamma_h, on a
    structured box and on the same tets as a plain TetMesh; both exactly symmetric."""
    from cutfem.geometry.mesh import TetMesh

    box = structured_box([-1, -1, -1], [1, 1, 1], cells=7)
    if not structured:
        box = TetMesh(np.array(box.points), np.array(box.tets))
    cut = cut_mesh(box, Sphere(RADIUS, center=CENTRE))
    V = CutSpace(cut, NEG)
    assert (V.elements.kuhn_types is not None) == structured

    @bilinear_form(symmetric=True)
    def terms(u, v, w):
        return -dot(w.n, u.grad) * v - dot(w.n, v.grad) * u + (w.gamma / w.h) * (u * v)

    for gamma in (10.0, 0.3):
        K = assemble(nitsche(cut.ds(), gamma), V)
        _close(K, assemble(terms * cut.ds(), V, gamma=gamma))
        _exactly_symmetric(K)


@pytest.mark.parametrize("weights", ["harmonic", "volume"])
def test_interface_nitsche_matches_reference_in_all_four_blocks(generic, weights):
    box, cut, values = generic
    VN, VP = CutSpace(cut, NEG), CutSpace(cut, POS)
    W = ProductSpace(VN, VP)
    a_neg, a_pos, gamma = 1.0, 7.0, 10.0
    dN, dP = _dof_map(VN), _dof_map(VP)
    n_neg = VN.n_dofs
    ref = np.zeros((W.n_dofs, W.n_dofs))
    for t, nodes, X, tri, n, h in _surface_triangles(cut, values):
        Ainv, G = _barycentric(X)
        if weights == "harmonic":
            k_neg = a_pos / (a_neg + a_pos)
            lam_pen = gamma * 2.0 * a_neg * a_pos / (a_neg + a_pos)
        else:
            P, _ = _side_polytope(X, values[nodes], NEG)
            k_neg = ConvexHull(P).volume / _tet_volume(X)
            lam_pen = 2.0 * gamma * (k_neg**2 * a_neg + (1 - k_neg) ** 2 * a_pos)
        k_pos = 1.0 - k_neg
        dn = G @ n
        sign = np.r_[np.ones(4), -np.ones(4)]  # [w] = w_NEG - w_POS
        flux = np.r_[k_neg * a_neg * dn, k_pos * a_pos * dn]  # {a n . grad w}
        pts, w = _triangle_points(tri)
        lam = _lam(Ainv, pts)
        local = np.zeros((8, 8))
        for q in range(3):
            jmp = sign * np.r_[lam[q], lam[q]]
            local += w[q] * (-np.outer(jmp, flux) - np.outer(flux, jmp) + lam_pen / h * np.outer(jmp, jmp))
        d = np.r_[dN[nodes], n_neg + dP[nodes]]
        ref[np.ix_(d, d)] += local
    K = assemble(interface_nitsche(cut.ds(), a_neg, a_pos, gamma, weights), W).toarray()
    blocks = [slice(0, n_neg), slice(n_neg, W.n_dofs)]
    for r in blocks:
        for c in blocks:
            _close(K[r, c], ref[r, c])
    assert np.max(np.abs(ref[blocks[0], blocks[1]])) > 0  # the coupling blocks are not empty
    _exactly_symmetric(K)


def test_ghost_penalty_matches_reference(generic):
    box, cut, values = generic
    V = CutSpace(cut, NEG)
    inside = values[box.tets] < 0
    neg_tets = np.flatnonzero(inside.any(axis=1))
    is_cut = inside.any(axis=1) & ~inside.all(axis=1)
    faces = {k: v for k, v in _interior_faces(box, neg_tets).items() if is_cut[v[0][0]] or is_cut[v[1][0]]}
    ghost = cut.ghost_facets(NEG)
    assert ghost.n_facets == len(faces)
    K = assemble(face_jump_penalty(cut.dF(ghost), h_power=1), V)
    _close(K, _reference_face_penalty(box, faces, V, 1))
    _exactly_symmetric(K)


def test_face_stabilization_on_cut_tets_matches_reference(generic):
    box, cut, values = generic
    V = CutSpace(cut)
    faces = _interior_faces(box, cut.tet_ids)
    assert cut.interior_facets(CUT).n_facets == len(faces)
    K = assemble(face_jump_penalty(cut.dF(cut.interior_facets(CUT))), V)
    _close(K, _reference_face_penalty(box, faces, V, 0))


@bilinear_form(symmetric=True)
def _uv(u, v, w):
    return u * v


@bilinear_form(symmetric=True)
def _grad_grad(u, v, w):
    return dot(u.grad, v.grad)


@bilinear_form(symmetric=True)
def _tgrad_tgrad(u, v, w):
    return dot(u.tgrad, v.tgrad)


@bilinear_form(symmetric=True)
def _normal_jumps(u, v, w):
    return w.h**w.power * dot(jump(u.grad), w.n) * dot(jump(v.grad), w.n)


@bilinear_form(symmetric=True)
def _normal_derivatives(u, v, w):
    return w.h * dot(w.n, u.grad) * dot(w.n, v.grad)


def test_gram_builtins_equal_the_same_integrands(generic):
    _, cut, _ = generic
    cases = []
    for side in (NEG, POS):
        V, dx = CutSpace(cut, side), cut.dx(side)
        dg = cut.dF(cut.ghost_facets(side))
        cases += [
            (mass(dx), _uv * dx, V, {}),
            (stiffness(dx), _grad_grad * dx, V, {}),
            (mass(cut.ds()), _uv * cut.ds(), V, {}),
            (face_jump_penalty(dg, h_power=1), _normal_jumps * dg, V, {"power": 1}),
        ]
    VS = CutSpace(cut, CUT)
    dF = cut.dF(cut.interior_facets(CUT))
    cases += [
        (mass(cut.ds()), _uv * cut.ds(), VS, {}),
        (tangential_stiffness(cut.ds()), _tgrad_tgrad * cut.ds(), VS, {}),
        (face_jump_penalty(dF), _normal_jumps * dF, VS, {"power": 0}),
        (normal_gradient_penalty(cut.dx(CUT), h_power=1), _normal_derivatives * cut.dx(CUT), VS, {}),
        (mass(cut.dx(CUT)), _uv * cut.dx(CUT), VS, {}),
    ]
    for builtin, generic_form, V, params in cases:
        A = assemble(builtin, V)
        _close(A, assemble(generic_form, V, **params))
        _exactly_symmetric(A)


def test_poisson_system_is_positive_definite(generic):
    _, cut, _ = generic
    V = CutSpace(cut, NEG)
    form = stiffness(cut.dx(NEG)) + nitsche(cut.ds(), 10.0) + 0.1 * face_jump_penalty(cut.dF(cut.ghost_facets(NEG)), h_power=1)
    K = assemble(form, V)
    _exactly_symmetric(K)
    eig = scipy.linalg.eigh(K.toarray(), eigvals_only=True)
    assert eig[0] > 1e-8 * eig[-1]


# ---------------------------------------------------------------------------------------------
# 7. bad input
# ---------------------------------------------------------------------------------------------


def test_field_integrated_where_it_does_not_live(generic):
    _, cut, _ = generic
    V = CutSpace(cut, CUT)
    with pytest.raises(ValueError, match="element set 'cut'"):
        assemble(mass(cut.dx(NEG)), V)
    with pytest.raises(ValueError, match="element set 'cut'"):
        assemble(_uv * cut.dx(NEG), V)
    with pytest.raises(ValueError, match="element set 'cut'"):
        assemble(stiffness(cut.dx(POS)), V)


@pytest.mark.parametrize("bad", [0.0, -1.0, np.nan])
def test_non_positive_coefficients_raise(generic, bad):
    _, cut, _ = generic
    ds = cut.ds()
    with pytest.raises(ValueError, match="a_neg"):
        interface_nitsche(ds, bad, 1.0)
    with pytest.raises(ValueError, match="a_pos"):
        interface_nitsche(ds, 1.0, bad)
    with pytest.raises(ValueError, match="gamma"):
        interface_nitsche(ds, 1.0, 1.0, gamma=bad)
    with pytest.raises(ValueError, match="gamma"):
        nitsche(ds, bad)
    with pytest.raises(ValueError, match="gamma"):
        nitsche(ds, bad, g=lambda x: x[..., 0])


def test_builtin_on_a_product_space_needs_a_field(generic):
    _, cut, _ = generic
    W = ProductSpace(CutSpace(cut, NEG), CutSpace(cut, POS))
    with pytest.raises(ValueError, match="field="):
        assemble(mass(cut.dx(NEG)), W)
    with pytest.raises(ValueError, match="field="):
        assemble(stiffness(cut.dx(NEG)), W)
    # with field= the block lands on that field's dofs and nowhere else
    K = assemble(stiffness(cut.dx(POS), field=1), W)
    KP = assemble(stiffness(cut.dx(POS)), W[1])
    n = W.offsets[1]
    assert K[:n, :].nnz == 0 and K[:, :n].nnz == 0
    _close(K[n:, n:], KP)


# ---------------------------------------------------------------------------------------------
# 8. product spaces
# ---------------------------------------------------------------------------------------------


def test_product_space_blocks_split_and_join(generic):
    _, cut, _ = generic
    VN, VP, VS = CutSpace(cut, NEG), CutSpace(cut, POS), CutSpace(cut, CUT)
    W = ProductSpace(VN, VP, VS)
    sizes = [VN.n_dofs, VP.n_dofs, VS.n_dofs]
    assert W.offsets.tolist() == [0, sizes[0], sizes[0] + sizes[1], sum(sizes)]
    assert W.n_dofs == sum(sizes)
    assert np.array_equal(W.dofs(1), np.arange(sizes[0], sizes[0] + sizes[1]))
    rng = np.random.default_rng(0)
    x = rng.normal(size=W.n_dofs)
    parts = W.split(x)
    assert [len(p) for p in parts] == sizes
    assert np.array_equal(parts[2], x[sizes[0] + sizes[1]:])
    assert np.array_equal(W.join(parts), x)
    X = rng.normal(size=(W.n_dofs, 3))
    assert np.array_equal(W.join(W.split(X)), X)
    with pytest.raises(ValueError, match="rows"):
        W.split(x[:-1])
    with pytest.raises(ValueError, match="blocks"):
        W.join(parts[:2])
    named = ProductSpace(bulk=VN, surface=VS)
    assert named.names == ["bulk", "surface"]
    assert named["surface"] is VS and named.index("surface") == 1
    assert np.array_equal(named.dofs("surface"), np.arange(VN.n_dofs, VN.n_dofs + VS.n_dofs))
    with pytest.raises(KeyError, match="bulk"):
        named.index("volume")
