"""Tests for cutfem.fem.assembly and for every built-in matrix against a plain reference assembly.

The references below are written from first principles and share no code with cutfem.fem.forms /
cutfem.fem.spaces: P1 basis functions from inverting the 4 x 4 (tet) or the 3 x 2 least-squares
(triangle) system, the exact P1 product formulas

    int_K phi_a phi_b = |K| (1 + delta_ab) / 12   (triangle),   |S| (1 + delta_ab) / 20   (tet),

normals and conormals from cross products, element loops in Python.  They run on small meshes: a
meshed sphere and torus, cut surfaces on a structured and on a randomly perturbed background,
and a cut volume (inside parts of tets split by scipy's Delaunay, independently of
cutfem.geometry.markers.side_subtetrahedra).  The penalties with a power of h use the local sizes: h_F the
longest edge of the face, h_T the longest edge of the tet.
"""

from collections import Counter, defaultdict

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial import Delaunay

from cutfem.fem.assembly import assemble_vector
from cutfem.geometry.cut import cut_mesh
from cutfem.fem.forms import assemble
from cutfem.fem.terms import (
    edge_jump_penalty,
    face_jump_penalty,
    mass,
    normal_gradient_penalty,
    stiffness,
    tangential_stiffness,
)
from cutfem.geometry.shapes import Sphere, Torus
from cutfem.geometry.markers import CUT, NEG
from cutfem.geometry.box import structured_box
from cutfem.geometry.mesh import TetMesh
from cutfem.fem.spaces import CutSpace, SurfaceP1Space
from cutfem.geometry.surface_meshes import sphere_mesh, torus_mesh
from cutfem import jit
from cutfem.fem import assembly_kernels

# ----------------------------------------------------------------------------------------------
# assemble_vector on synthetic blocks
# ----------------------------------------------------------------------------------------------


def test_assemble_vector_scalar_and_components():
    dofs = np.array([[0, 1, 2], [2, 3, 0]])
    local = np.array([[1.0, 2.0, 3.0], [10.0, 20.0, 30.0]])
    np.testing.assert_array_equal(assemble_vector(dofs, local, 5), [31.0, 2.0, 13.0, 20.0, 0.0])
    local3 = np.stack([local, -local, 2 * local], axis=2)  # (m, k, 3)
    out = assemble_vector(dofs, local3, 5)
    assert out.shape == (5, 3)
    np.testing.assert_array_equal(out[:, 1], -np.array([31.0, 2.0, 13.0, 20.0, 0.0]))
    np.testing.assert_array_equal(out[:, 2], 2 * np.array([31.0, 2.0, 13.0, 20.0, 0.0]))


# ----------------------------------------------------------------------------------------------
# first-principles P1 reference assembly
# ----------------------------------------------------------------------------------------------

MASS3 = (np.ones((3, 3)) + np.eye(3)) / 12.0  # int_K phi_a phi_b / |K| on a triangle
MASS4 = (np.ones((4, 4)) + np.eye(4)) / 20.0  # on a tetrahedron


def tet_basis(X):
    """Affine barycentric functions of the tet with vertex rows X (4, 3): lambda_i(x) = c[i] + g[i] . x.

    The 4 x 4 matrix T with columns (1, x_j) satisfies T^{-1} T = I, i.e. row i of T^{-1} evaluates
    lambda_i at the vertices to delta_ij.
    """
    T = np.vstack([np.ones(4), np.asarray(X, float).T])
    Ti = np.linalg.inv(T)
    return Ti[:, 0], Ti[:, 1:]


def triangle_basis_gradients(P):
    """Surface gradients (3, 3) of the P1 basis on the triangle with vertex rows P, from
    G = E (E^T E)^{-1}, E = [x1 - x0, x2 - x0]: g_a . e_b = delta_ab and g_a in span(E)."""
    E = np.column_stack([P[1] - P[0], P[2] - P[0]])
    G = E @ np.linalg.inv(E.T @ E)
    return np.array([-G[:, 0] - G[:, 1], G[:, 0], G[:, 1]])


def unit(v):
    return v / np.linalg.norm(v)


def triangle_area_normal(P):
    c = np.cross(P[1] - P[0], P[2] - P[0])
    return 0.5 * np.linalg.norm(c), unit(c)


def reference_meshed(points, triangles, h):
    """Mass, tangential stiffness and J_E (with mesh size h) of a triangulated closed surface."""
    n = len(points)
    M, A, JE = np.zeros((n, n)), np.zeros((n, n)), np.zeros((n, n))
    grads, normals = [], []
    for tri in triangles:
        P = points[tri]
        area, nrm = triangle_area_normal(P)
        G = triangle_basis_gradients(P)
        grads.append(G)
        normals.append(nrm)
        idx = np.ix_(tri, tri)
        M[idx] += area * MASS3
        A[idx] += area * G @ G.T
    edges = defaultdict(list)  # sorted node pair -> [(triangle, opposite node)]
    for k, tri in enumerate(triangles):
        for a in range(3):
            i, j, o = tri[a], tri[(a + 1) % 3], tri[(a + 2) % 3]
            edges[(min(i, j), max(i, j))].append((k, o))
    for (i, j), owners in edges.items():
        assert len(owners) == 2
        d = points[j] - points[i]
        length = np.linalg.norm(d)
        c = np.zeros(n)
        for k, o in owners:
            t = unit(np.cross(d, normals[k]))  # in the plane of K, orthogonal to E
            if t @ (points[o] - points[i]) > 0:  # must point away from K's third vertex
                t = -t
            np.add.at(c, triangles[k], grads[k] @ t)
        nz = np.flatnonzero(c)
        JE[np.ix_(nz, nz)] += h * length * np.outer(c[nz], c[nz])
    return M, A, JE


def longest_edge(X):
    """The longest edge of the simplex with vertex rows X."""
    return max(np.linalg.norm(X[a] - X[b]) for a in range(len(X)) for b in range(a))


def reference_cut(cut, h, face_h_powers=(0.0, 2.0), normal_h_powers=(1.0, 0.0)):
    """Mass, tangential stiffness, J_E (with the global h), and J_F and the normal-gradient penalty
    for each power a of the local h (dicts a -> matrix: h_F^a per face, h_T^a per tet) of a cut P1
    space, in the numbering of the active nodes (cut.points, cut.tets); pieces from cut.triangles."""
    pts, tets = cut.points, cut.tets
    n = len(pts)
    basis = [tet_basis(pts[T]) for T in tets]
    M, A, JE = (np.zeros((n, n)) for _ in range(3))
    JF = {a: np.zeros((n, n)) for a in face_h_powers}
    S = {a: np.zeros((n, n)) for a in normal_h_powers}

    piece_normal = {}
    piece_vertices = defaultdict(set)
    piece_edges = defaultdict(Counter)
    for tri, k in zip(cut.triangles, cut.triangle_tets):
        V = cut.vertices[tri]
        area, nrm = triangle_area_normal(V)
        piece_normal.setdefault(k, nrm)  # all triangles of a piece are coplanar
        c0, g = basis[k]
        vals = c0[:, None] + g @ V.T  # (4, 3): lambda_i at the triangle's vertices
        Pg = g - np.outer(g @ nrm, nrm)
        idx = np.ix_(tets[k], tets[k])
        M[idx] += area * vals @ MASS3 @ vals.T
        A[idx] += area * Pg @ Pg.T
        piece_vertices[k].update(tri.tolist())
        for a in range(3):
            e = (min(tri[a], tri[(a + 1) % 3]), max(tri[a], tri[(a + 1) % 3]))
            piece_edges[k][e] += 1

    # J_E: polygon edges (appearing once in their piece; a quad's diagonal appears twice)
    owners = defaultdict(list)
    for k, counts in piece_edges.items():
        for e, times in counts.items():
            if times == 1:
                owners[e].append(k)
    for (i, j), ks in owners.items():
        assert len(ks) == 2, "every edge of a closed S_h separates two pieces"
        p0, p1 = cut.vertices[i], cut.vertices[j]
        d = p1 - p0
        c = np.zeros(n)
        for k in ks:
            t = unit(np.cross(d, piece_normal[k]))
            centroid = cut.vertices[sorted(piece_vertices[k])].mean(axis=0)
            if t @ (0.5 * (p0 + p1) - centroid) < 0:  # out of the (convex) piece
                t = -t
            np.add.at(c, tets[k], basis[k][1] @ t)
        nz = np.flatnonzero(c)
        JE[np.ix_(nz, nz)] += h * np.linalg.norm(d) * np.outer(c[nz], c[nz])

    # J_F: faces shared by two active tets; the jump merged over the five distinct nodes
    faces = defaultdict(list)
    for k, T in enumerate(tets):
        for a in range(4):
            faces[tuple(sorted(np.delete(T, a).tolist()))].append((k, T[a]))
    for face, sides in faces.items():
        if len(sides) != 2:
            continue
        X = pts[list(face)]
        area, nF = triangle_area_normal(X)
        (k1, o1), (k2, _) = sides
        if nF @ (pts[o1] - X[0]) > 0:  # outward from the first tet
            nF = -nF
        c = np.zeros(n)
        np.add.at(c, tets[k1], basis[k1][1] @ nF)
        np.add.at(c, tets[k2], -(basis[k2][1] @ nF))
        nz = np.flatnonzero(c)
        for a in face_h_powers:
            JF[a][np.ix_(nz, nz)] += longest_edge(X) ** a * area * np.outer(c[nz], c[nz])

    # normal-gradient volume penalty over the whole active tets, n = piece normal
    for k, T in enumerate(tets):
        X = pts[T]
        vol = abs(np.linalg.det(X[1:] - X[0])) / 6.0
        gn = basis[k][1] @ piece_normal[k]
        for a in normal_h_powers:
            S[a][np.ix_(T, T)] += longest_edge(X) ** a * vol * np.outer(gn, gn)
    return M, A, JE, JF, S


def reference_volume(background, phi):
    """Mass and stiffness over {phi_h < 0} in background node numbering: the inside part of a
    cut tet is the convex hull of its inside nodes and the zeros of phi_h on its edges, split by
    Delaunay; the exact P1 product formula on every sub-tet."""
    pts, tets = background.points, background.tets
    N = len(pts)
    M, K = np.zeros((N, N)), np.zeros((N, N))
    for T in tets:
        v = phi[T]
        inside = v < 0
        if not inside.any():
            continue
        X = pts[T]
        c0, g = tet_basis(X)
        if inside.all():
            subs = [X]
        else:
            corners = [X[a] for a in range(4) if inside[a]]
            for a in np.flatnonzero(inside):
                for b in np.flatnonzero(~inside):
                    t = v[a] / (v[a] - v[b])
                    corners.append(X[a] + t * (X[b] - X[a]))
            corners = np.array(corners)
            subs = [corners[s] for s in Delaunay(corners).simplices]
        idx = np.ix_(T, T)
        for Y in subs:
            vol = abs(np.linalg.det(Y[1:] - Y[0])) / 6.0
            vals = c0[:, None] + g @ Y.T
            M[idx] += vol * vals @ MASS4 @ vals.T
            K[idx] += vol * g @ g.T
    return M, K


def assert_matrix_equal(actual, expected, rel=1e-12):
    actual = actual.toarray() if sp.issparse(actual) else np.asarray(actual)
    scale = np.abs(expected).max()
    assert scale > 0
    np.testing.assert_allclose(actual, expected, rtol=0, atol=rel * scale)


# ----------------------------------------------------------------------------------------------
# meshed surfaces
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make",
    [lambda: sphere_mesh(1, radius=0.9), lambda: torus_mesh(8, "perturbed-flipped", seed=3)],
    ids=["sphere", "torus"],
)
def test_meshed_matrices_match_reference(make):
    mesh = make()
    V = SurfaceP1Space(mesh)
    pts, tris = np.asarray(mesh.points), np.asarray(mesh.triangles)
    M, A, JE = reference_meshed(pts, tris, V.h)
    dS = mesh.ds()
    assert_matrix_equal(assemble(mass(dS), V), M)
    assert_matrix_equal(assemble(tangential_stiffness(dS), V), A)
    assert_matrix_equal(assemble(edge_jump_penalty(dS), V), JE)
    assert_matrix_equal(assemble(edge_jump_penalty(dS, h=0.37), V), JE * 0.37 / V.h)


# ----------------------------------------------------------------------------------------------
# cut surfaces
# ----------------------------------------------------------------------------------------------


def perturbed_box(lower, upper, cells, amount, seed):
    """A structured box whose interior nodes are moved at random by up to ``amount`` cell sizes:
    generic tetrahedra, same connectivity."""
    box = structured_box(lower, upper, cells=cells)
    pts = np.array(box.points)
    interior = np.ones(len(pts), bool)
    interior[box.boundary_nodes] = False
    rng = np.random.default_rng(seed)
    pts[interior] += amount * box.spacing * rng.uniform(-1, 1, size=(interior.sum(), 3))
    return TetMesh(pts, np.array(box.tets))


CUT_CASES = {
    "sphere-structured": lambda: cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), Sphere(0.63, [0.03, -0.02, 0.05])),
    "sphere-perturbed": lambda: cut_mesh(perturbed_box([-1, -1, -1], [1, 1, 1], 7, 0.25, seed=4), Sphere(0.6, [0.02, 0.04, -0.03])),
    "torus-structured": lambda: cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], cells=(10, 10, 4)), Torus(1.0, 0.45)),
}


@pytest.fixture(scope="module", params=sorted(CUT_CASES))
def cut_case(request):
    cut = CUT_CASES[request.param]()
    V = CutSpace(cut)
    return V, reference_cut(cut, V.h, face_h_powers=(0.0, 2.0), normal_h_powers=(1.0, 0.0))


def test_cut_mass_and_stiffness_match_reference(cut_case):
    V, (M, A, _, _, _) = cut_case
    dS = V.cut.ds()
    assert_matrix_equal(assemble(mass(dS), V), M)
    assert_matrix_equal(assemble(tangential_stiffness(dS), V), A)


def test_cut_edge_jump_matches_reference(cut_case):
    V, (_, _, JE, _, _) = cut_case
    assert_matrix_equal(assemble(edge_jump_penalty(V.cut.ds()), V), JE)


def test_cut_face_jump_matches_reference(cut_case):
    V, (_, _, _, JF, _) = cut_case
    dF = V.cut.dF(V.cut.interior_facets(CUT))
    assert_matrix_equal(assemble(face_jump_penalty(dF), V), JF[0.0])
    assert_matrix_equal(assemble(face_jump_penalty(dF, h_power=2.0), V), JF[2.0])


def test_cut_normal_gradient_penalty_matches_reference(cut_case):
    V, (_, _, _, _, S) = cut_case
    dT = V.cut.dx(CUT)
    assert_matrix_equal(assemble(normal_gradient_penalty(dT), V), S[1.0])
    assert_matrix_equal(assemble(normal_gradient_penalty(dT, h_power=0.0), V), S[0.0])


# ----------------------------------------------------------------------------------------------
# cut volume
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("perturbed", [False, True], ids=["structured", "perturbed"])
def test_volume_mass_and_stiffness_match_reference(perturbed):
    if perturbed:
        bg = perturbed_box([-1, -1, -1], [1, 1, 1], 5, 0.25, seed=7)
    else:
        bg = structured_box([-1, -1, -1], [1, 1, 1], cells=5)
        bg = TetMesh(np.array(bg.points), np.array(bg.tets))
    ls = Sphere(0.71, [0.05, -0.03, 0.02])
    cut = cut_mesh(bg, ls)
    V = CutSpace(cut, NEG)
    M, K = reference_volume(bg, ls.value(bg.points))
    ids = V.node_ids
    # the space's dofs are exactly the nodes touched by the reference
    touched = np.flatnonzero(np.abs(M).sum(axis=1) > 0)
    np.testing.assert_array_equal(np.sort(ids), touched)
    assert_matrix_equal(assemble(mass(cut.dx(NEG)), V), M[np.ix_(ids, ids)])
    assert_matrix_equal(assemble(stiffness(cut.dx(NEG)), V), K[np.ix_(ids, ids)])


@pytest.mark.parametrize("cells", [5, (5, 4, 6)], ids=["cubes", "anisotropic"])
def test_volume_stiffness_on_a_structured_box_matches_reference(cells, monkeypatch):
    """The lattice route of the mass and the stiffness (StructuredBox element sets, summed in lattice
    slots by LatticeSum in blocks of GRAM_ROWS // 4 tets) against the element loop: the same matrix, exactly
    symmetric, with zero row sums (the gradients of the basis sum to zero), and the entries that
    cancel exactly on a uniform lattice left out of the pattern as the Gram product leaves them."""
    import cutfem.fem.assembly as assembly
    from cutfem.fem.closed_forms import _gradient_matrix

    monkeypatch.setattr(assembly, "GRAM_ROWS", 4 * 37)
    bg = structured_box([-1, -1, -1], [1, 1, 1], cells=cells)
    ls = Sphere(0.71, [0.05, -0.03, 0.02])
    cut = cut_mesh(bg, ls)
    V = CutSpace(cut, NEG)
    assert V.elements.kuhn_types is not None
    M, K = reference_volume(bg, ls.value(bg.points))
    ids = V.node_ids
    assert_matrix_equal(assemble(mass(cut.dx(NEG)), V), M[np.ix_(ids, ids)])
    A = assemble(stiffness(cut.dx(NEG)), V)
    assert_matrix_equal(A, K[np.ix_(ids, ids)])
    assert abs(A - A.T).max() == 0.0
    np.testing.assert_allclose(np.asarray(A.sum(axis=1)).ravel(), 0.0, atol=1e-13)
    G = _gradient_matrix(V, V.gradients_of, cut.dx(NEG).part_volumes)
    assert A.nnz == G.nnz
    np.testing.assert_allclose(A.toarray(), G.toarray(), rtol=0, atol=1e-14)
    # whole tets of an element set (ElementVolume): against the simplex route of the same tets as a TetMesh
    plain = cut_mesh(TetMesh(np.array(bg.points), np.array(bg.tets)), ls)
    Vp = CutSpace(plain, NEG)
    np.testing.assert_array_equal(Vp.node_ids, ids)
    whole = assemble(mass(cut.dx(cut.elements(NEG))), V)
    assert_matrix_equal(whole, assemble(mass(plain.dx(plain.elements(NEG))), Vp).toarray())
    assert whole.sum() == pytest.approx(V.elements.volumes.sum(), rel=1e-13)


def test_tangential_stiffness_on_a_structured_box_matches_the_gram_route():
    """The lattice route of the tangential stiffness (cut tets of a StructuredBox: a table of
    Kuhn gradient products less a rank-one term per tet) against the Gram product of the same
    tangential gradients and against the simplex route of the same tets as a TetMesh: the same
    matrix to round-off, exactly symmetric, constants in its kernel, and a linear function x . g
    gives sum_K |K| |P_h g|^2."""
    from cutfem.fem.terms import tangential_stiffness
    from cutfem.fem.closed_forms import _gradient_matrix

    bg = structured_box([-1, -1, -1], [1, 1, 1], cells=(6, 5, 7))
    ls = Sphere(0.71, [0.05, -0.03, 0.02])
    cut = cut_mesh(bg, ls)
    V = CutSpace(cut)
    assert V.elements.kuhn_types is not None
    dS = cut.ds()
    A = assemble(tangential_stiffness(dS), V)
    G = _gradient_matrix(V, V.tangential_gradients_of, dS.piece_areas)
    scale = abs(G).max()
    np.testing.assert_allclose(A.toarray(), G.toarray(), rtol=0, atol=1e-14 * scale)
    assert abs(A - A.T).max() == 0.0
    np.testing.assert_allclose(A @ np.ones(V.n_dofs), 0.0, atol=1e-13 * scale)
    plain = cut_mesh(TetMesh(np.array(bg.points), np.array(bg.tets)), ls)
    Vp = CutSpace(plain)
    np.testing.assert_array_equal(Vp.node_ids, V.node_ids)
    np.testing.assert_allclose(A.toarray(), assemble(tangential_stiffness(plain.ds()), Vp).toarray(), rtol=0, atol=1e-13 * scale)
    g = np.array([0.3, -1.2, 0.7])
    u = V.dof_points @ g
    tangential = g - np.outer(dS.normals @ g, np.ones(3)) * dS.normals
    assert u @ A @ u == pytest.approx(np.sum(dS.piece_areas * np.einsum("md,md->m", tangential, tangential)), rel=1e-12)


# ----------------------------------------------------------------------------------------------
# the assembly benchmark study, at a tiny size
# ----------------------------------------------------------------------------------------------


def test_assembly_benchmark_runs_and_records(tmp_path):
    import json

    from cutfem.studies import assembly_benchmark

    data = assembly_benchmark.run(tmp_path, spacings=[0.4], repeat=1, cold_repeat=1)
    for suffix in (".json", ".csv", ".png"):
        assert (tmp_path / f"assembly_benchmark{suffix}").stat().st_size > 0
    (row,) = json.loads((tmp_path / "assembly_benchmark.json").read_text())["rows"]
    assert row == pytest.approx(data["rows"][0], rel=1e-5)  # the JSON holds six significant digits (studies.common.save_json)
    assert row["background_nodes"] == 9 * 9 * 4  # 8 x 8 x 3 cubes of side 0.4
    assert row["h"] == pytest.approx(324 ** (-1 / 3), rel=1e-5)
    assert row["mass_nnz"] == row["stiffness_nnz"] < row["face_jump_nnz"]  # J_F couples face neighbours
    assert all(row[k] > 0 for k in row if k.endswith(("_cold", "_warm", "_seconds")))
    assert row["together_cold_per_million_tets"] == pytest.approx(row["together_cold"] / row["active_tets"] * 1e6, rel=2e-5)


def test_assembly_benchmark_refuses_impossible_spacings(tmp_path, capsys):
    """A spacing whose cut needs more memory than there is, or --spacings together with a size
    flag (which would be ignored), end with a usage error that names --spacings, not a traceback."""
    from cutfem.studies import assembly_benchmark

    with pytest.raises(SystemExit) as exc:
        assembly_benchmark.main(["--out", str(tmp_path), "--spacings", "0.0005", "--quiet"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--spacings: the cut of" in err and "spacing 0.0005" in err and "coarser spacing" in err
    with pytest.raises(SystemExit) as exc:
        assembly_benchmark.main(["--out", str(tmp_path), "--spacings", "0.4", "--full", "--quiet"])
    assert exc.value.code == 2
    assert "--spacings" in capsys.readouterr().err
    assert not (tmp_path / "assembly_benchmark.json").exists()


def test_gram_leaves_the_callers_arrays_alone():
    """The rows of E are sorted in place; that must not reorder the dofs or values handed in
    (int32 and int64 dofs, which may be used without a copy)."""
    from cutfem.fem.assembly import gram, row_operator

    rng = np.random.default_rng(5)
    for dtype in (np.int32, np.int64):
        dofs = rng.integers(0, 30, (25, 4)).astype(dtype)
        values = rng.standard_normal((25, 4))
        d0, v0 = dofs.copy(), values.copy()
        E = row_operator(dofs, values, 30)
        G = gram(dofs, values, 30)
        np.testing.assert_array_equal(dofs, d0)
        np.testing.assert_array_equal(values, v0)
        D = np.zeros((25, 30))
        np.add.at(D, (np.repeat(np.arange(25), 4), d0.reshape(-1)), v0.reshape(-1))
        np.testing.assert_allclose(E.toarray(), D, atol=1e-15)
        np.testing.assert_allclose(G.toarray(), D.T @ D, atol=1e-13)


def test_gram_in_blocks_of_rows(monkeypatch):
    """Above GRAM_ROWS rows the Gram matrix is summed block by block: the same matrix, exactly
    symmetric, and the caller's arrays untouched (the blocks are sorted in place)."""
    import cutfem.fem.assembly as assembly

    rng = np.random.default_rng(7)
    dofs = rng.integers(0, 40, (103, 4))
    values = rng.standard_normal((103, 4))
    d0, v0 = dofs.copy(), values.copy()
    whole = assembly.gram(dofs, values, 40).toarray()
    monkeypatch.setattr(assembly, "GRAM_ROWS", 10)
    blocked = assembly.gram(dofs, values, 40)
    np.testing.assert_array_equal(dofs, d0)
    np.testing.assert_array_equal(values, v0)
    np.testing.assert_allclose(blocked.toarray(), whole, rtol=0, atol=1e-12)
    assert (blocked - blocked.T).nnz == 0 or np.abs((blocked - blocked.T).data).max() == 0.0
    D = np.zeros((103, 40))
    np.add.at(D, (np.repeat(np.arange(103), 4), d0.reshape(-1)), v0.reshape(-1))
    np.testing.assert_allclose(blocked.toarray(), D.T @ D, atol=1e-12)


def test_lattice_sum_refuses_pairs_that_are_not_lattice_neighbours():
    """LatticeSum keeps 13 slots a node: a pair of nodes further apart than two face-adjacent Kuhn
    tets has no slot, and is reported instead of dropped; the Gram rows it sums otherwise equal the
    sparse product's, exactly symmetric, with the 13 offsets those of the box's node ids."""
    from cutfem.fem.assembly import LatticeSum, gram
    from cutfem.geometry.box import kuhn_neighbour_offsets

    box = structured_box([0, 0, 0], [1, 1, 1], cells=4)
    offsets = kuhn_neighbour_offsets()
    assert len(offsets) == 13 and len({tuple(o) for o in offsets}) == 13
    assert np.all(np.diff(box.neighbour_id_offsets) > 0)
    ids = np.arange(box.n_points)
    lattice = LatticeSum(ids, box)
    with pytest.raises(ValueError, match="not nodes of one Kuhn tet or of two face-adjacent tets"):
        lattice.add_rows(np.array([[0, 3]]), np.array([[1.0, 2.0]]))  # (3, 0, 0) apart
    # rows on the node pairs of the 13 offsets from an interior node, and a repeated dof
    centre = int(box.node_id(np.array([2, 2, 2])))
    partners = centre + box.neighbour_id_offsets
    dofs = np.stack([np.full(13, centre), partners, partners], axis=1)
    values = np.random.default_rng(3).standard_normal((13, 3))
    A = LatticeSum(ids, box).add_rows(dofs, values).matrix()
    np.testing.assert_allclose(A.toarray(), gram(dofs, values, box.n_points).toarray(), rtol=0, atol=1e-14)
    assert abs(A - A.T).max() == 0.0
    S = sp.csr_matrix((A.data.copy(), A.indices.copy(), A.indptr.copy()), shape=A.shape)
    S.has_sorted_indices = False
    S.sort_indices()  # the CSR arrays were written sorted, without duplicates
    np.testing.assert_array_equal(S.indices, A.indices)
    assert np.all(np.diff(A.indices.reshape(-1)[A.indptr[1]:A.indptr[2]]) > 0)


def test_face_penalty_sums_on_all_cores(monkeypatch):
    """The face penalty adds its faces in chunks (assembly_kernels.scatter_chunks): chunks of one parity
    touch disjoint ranges of nodes, the matrix equals the one of a single pass in face order to
    round-off and is bitwise the same on one thread as on all; faces in random order get one
    chunk."""
    import numba


    cut = cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.05), Torus())
    V = CutSpace(cut)
    dF = cut.dF(cut.interior_facets(CUT))
    seen = []
    chunks = assembly_kernels.scatter_chunks
    monkeypatch.setattr(assembly_kernels, "scatter_chunks", lambda dofs, owners, counts=jit.SWEEP_CHUNKS: seen.append(
        (dofs, np.asarray(owners).reshape(len(owners), -1), chunks(dofs, owners, counts))) or seen[-1][2])
    J = assemble(face_jump_penalty(dF), V)
    dofs, pairs, bounds = seen[-1]
    k = len(bounds) - 1
    assert k in (4, 8) and bounds[-1] == len(pairs)
    ranges = [(dofs[pairs[a:b]].min(), dofs[pairs[a:b]].max()) for a, b in zip(bounds[:-1], bounds[1:])]
    for c in range(k):
        for d in range(c + 2, k, 2):
            assert ranges[c][1] < ranges[d][0] or ranges[d][1] < ranges[c][0]
    shuffled = pairs[np.random.default_rng(0).permutation(len(pairs))]
    np.testing.assert_array_equal(chunks(dofs, shuffled), [0, len(pairs)])
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        J1 = assemble(face_jump_penalty(dF), V)
    finally:
        numba.set_num_threads(threads)
    for a, b in ((J.indptr, J1.indptr), (J.indices, J1.indices), (J.data, J1.data)):
        np.testing.assert_array_equal(a, b)
    monkeypatch.setattr(assembly_kernels, "scatter_chunks", lambda dofs, owners, counts=None: np.array([0, len(owners)]))
    J0 = assemble(face_jump_penalty(dF), V)
    assert abs(J0 - J).max() <= 1e-14 * abs(J0).max()


def test_scatter_chunks_without_owners_is_each_element_its_own_row():
    """owners None (element e reads row e of dofs) gives the chunks of the explicit owners 0..E-1:
    for rows along a lattice (several chunks) and for rows in random order (one chunk)."""

    base = np.arange(4000)[:, None] + np.array([0, 1, 7, 40])
    for dofs in (base, base[np.random.default_rng(1).permutation(len(base))]):
        explicit = assembly_kernels.scatter_chunks(dofs, np.arange(len(dofs))[:, None])
        np.testing.assert_array_equal(assembly_kernels.scatter_chunks(dofs, None), explicit)
    assert len(assembly_kernels.scatter_chunks(base, None)) > 2 and len(explicit) == 2


@pytest.mark.parametrize("threads", [1, 2])
def test_lattice_csr_by_chunks_is_the_csr_of_the_slots(threads):
    """The CSR arrays written from the lattice slots on the available cores (rows in chunks,
    mirrors placed by the masks of incoming slots) equal scipy's CSR of the same entries: the
    diagonal, each nonzero slot (a, partner) and its mirror; on one thread and on two."""
    import numba

    from cutfem.fem.assembly import LatticeSum

    cut = cut_mesh(structured_box([-1.6, -1.6, -0.7], [1.6, 1.6, 0.7], cells=(40, 40, 18)), Torus(1.0, 0.5))
    V = CutSpace(cut)
    assert V.n_dofs > 8 * 64  # enough rows for the chunks
    lattice = LatticeSum(V.node_ids, cut.background)
    rng = np.random.default_rng(5)
    lattice.add_elements(V.element_dofs, rng.random((len(V.element_dofs), 6)), rng.random((len(V.element_dofs), 4)))
    sums, partner, diagonal = lattice._slots()
    n = V.n_dofs
    a = np.repeat(np.arange(n), 13)
    nz = sums != 0
    ref = sp.coo_matrix((np.concatenate([diagonal, sums[nz], sums[nz]]),
                         (np.concatenate([np.arange(n), a[nz], partner[nz]]), np.concatenate([np.arange(n), partner[nz], a[nz]]))),
                        shape=(n, n)).tocsr()
    ref.sort_indices()
    before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        A = lattice.matrix()
    finally:
        numba.set_num_threads(before)
    for x, y in ((A.indptr, ref.indptr), (A.indices, ref.indices), (A.data, ref.data)):
        np.testing.assert_array_equal(x, y)
    assert abs(A - A.T).max() == 0.0
