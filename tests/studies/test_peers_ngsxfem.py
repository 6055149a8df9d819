"""cutfem.studies.peers_ngsxfem: the peer's side, on cutfem's own tets. The geometry helpers are
tested always; what needs ngsolve and xfem is skipped without them (the ``ngsxfem`` fixture,
tests/studies/conftest.py)."""

import numpy as np
import pytest

from cutfem.studies import peers, peers_ngsxfem


def test_kuhn_boundary_triangles_cover_the_box_outward():
    from cutfem.geometry.box import structured_box

    box = structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], cells=[4, 3, 2])
    tri = peers_ngsxfem.kuhn_boundary_triangles(box)
    nx, ny, nz = box.cells
    assert len(tri) == 4 * (nx * ny + ny * nz + nx * nz)
    # the same triangles as the boundary faces of the full face topology
    assert {tuple(sorted(t)) for t in tri.tolist()} == {tuple(f) for f in box.faces[box.boundary_faces].tolist()}
    p = box.points[tri]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.all(np.einsum("ij,ij->i", cross, p.mean(axis=1)) > 0)  # outward (box centred at 0)
    assert 0.5 * np.linalg.norm(cross, axis=1).sum() == pytest.approx(2 * (3.2 * 3.2 + 2 * 3.2 * 1.2))


def test_collapsed_tets_are_the_difference_of_the_zero_rules():
    """Tets with a negative node, zero nodes (one or two) and no positive node: found around the
    zero nodes only, and equal to the brute-force set."""
    from cutfem.geometry.box import structured_box

    box = structured_box([0, 0, 0], [1, 1, 1], cells=3)
    rng = np.random.default_rng(1)
    values = rng.choice([-1.0, 0.0, 1.0], size=box.n_points, p=[0.45, 0.2, 0.35])
    v = values[box.tets]
    nz = (v == 0).sum(axis=1)
    brute = np.flatnonzero((v < 0).any(axis=1) & ~(v > 0).any(axis=1) & (nz >= 1) & (nz <= 2))
    assert brute.size > 0
    assert np.array_equal(np.sort(peers_ngsxfem.collapsed_tets(box, values)), brute)
    assert peers_ngsxfem.collapsed_tets(box, np.ones(box.n_points)).size == 0


def test_ngsolve_mesh_is_the_structured_box(ngsxfem):
    import ngsolve

    from cutfem.geometry.shapes import Torus
    from cutfem.problems.common import background_for

    box = background_for(Torus(), 0.4)
    mesh = peers_ngsxfem.ngsolve_mesh(box)
    assert (mesh.nv, mesh.ne) == (box.n_points, box.n_tets)
    a, b, c = box.upper - box.lower
    assert ngsolve.Integrate(1, mesh) == pytest.approx(a * b * c)
    assert ngsolve.Integrate(1, mesh, ngsolve.BND) == pytest.approx(2 * (a * b + b * c + a * c))
    # vertex k is point k
    assert np.allclose([mesh.vertices[k].point for k in (0, 7, box.n_points - 1)], box.points[[0, 7, box.n_points - 1]])


def test_exact_field_matches_cutfem(ngsxfem):
    from cutfem.geometry.shapes import Torus
    from cutfem.problems.common import background_for

    torus = Torus(center=tuple(peers.SHIFT))
    mesh = peers_ngsxfem.ngsolve_mesh(background_for(torus, 0.4, box=peers.BOX))
    cf = peers_ngsxfem.torus_exact_cf(torus)
    pts = np.array([[1.3, 0.2, 0.3], [-0.4, -0.5, -0.2], [0.1, 1.45, 0.05]])
    got = np.array([cf(mesh(*p)) for p in pts])
    assert np.allclose(got, torus.exact_mean_curvature_vector(pts), rtol=1e-12, atol=1e-12)


def test_kuhn_face_h_is_the_longest_edge_of_each_facet(ngsxfem):
    """sum over the facets of every tet of |F| h_F: NGSolve's integral of kuhn_face_h against the
    longest edges of cutfem's face table."""
    import ngsolve

    from cutfem.geometry.box import structured_box

    box = structured_box([0, 0, 0], [0.75, 0.5, 0.5], spacing=0.25)
    got = ngsolve.Integrate(peers_ngsxfem.kuhn_face_h(0.25) * ngsolve.dx(element_boundary=True), peers_ngsxfem.ngsolve_mesh(box))
    p = box.points[box.faces]
    longest = np.max([np.linalg.norm(p[:, i] - p[:, j], axis=1) for i, j in ((0, 1), (1, 2), (0, 2))], axis=0)
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    times = np.full(len(area), 2.0)  # interior faces belong to two tets
    times[box.boundary_faces] = 1.0
    assert got == pytest.approx(np.sum(times * area * longest), rel=1e-12)


def test_stokes_exact_fields_match_cutfem(ngsxfem):
    """u, grad u, p and f = -nu Lap u + grad p of ngsxfem's Stokes data against cutfem's sympy ones."""
    from cutfem.geometry.box import structured_box
    from cutfem.problems.stokes import PRESSURE, VELOCITY

    nu = 0.7
    mesh = peers_ngsxfem.ngsolve_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=2))
    u, grad_u, p, f = peers_ngsxfem.stokes_exact_cf(nu)
    pts = np.array([[0.3, -0.2, 0.5], [-0.7, 0.6, 0.1], [0.05, 0.9, -0.4]])

    def at(cf):
        return np.array([cf(mesh(*x)) for x in pts])

    assert np.allclose(at(u), VELOCITY(pts), rtol=1e-13, atol=1e-14)
    assert np.allclose(at(grad_u).reshape(-1, 3, 3), VELOCITY.grad(pts), rtol=1e-13, atol=1e-14)
    assert np.allclose(at(p), PRESSURE(pts), rtol=1e-13, atol=1e-14)
    assert np.allclose(at(f), -nu * VELOCITY.laplacian(pts) + PRESSURE.grad(pts), rtol=1e-13, atol=1e-14)


def test_bordered_matrix_and_block_preconditioner(ngsxfem):
    """bordered(K, c) = [[K, c], [c^T, 0]] from lower or whole storage; the block preconditioner keeps
    K's velocity block, negates its pressure block, adds S and the multiplier's number."""
    import ngsolve

    rng = np.random.default_rng(0)
    K = rng.standard_normal((5, 5))
    K = K + K.T
    K[0, 1] = K[1, 0] = 0.0  # a stored zero
    r, c = np.nonzero(np.ones((5, 5)))
    whole = ngsolve.la.SparseMatrixd.CreateFromCOO(r, c, K[r, c], 5, 5)
    low = r >= c
    lower = ngsolve.la.SparseMatrixd.CreateFromCOO(r[low], c[low], K[r[low], c[low]], 5, 5)
    vec = whole.CreateColVector()
    vec.FV().NumPy()[:] = [0.0, 1.0, 2.0, 0.0, 3.0]
    expect = np.zeros((6, 6))
    expect[:5, :5], expect[:5, 5], expect[5, :5] = K, vec.FV().NumPy(), vec.FV().NumPy()
    for m in (whole, lower):
        B = peers_ngsxfem.bordered(m, vec)
        assert np.array_equal(_dense(B), expect)
    S = ngsolve.la.SparseMatrixd.CreateFromCOO([3, 4, 3, 4], [3, 4, 4, 3], [2.0, 2.0, 0.5, 0.5], 5, 5)
    P = _dense(peers_ngsxfem._block_preconditioner(peers_ngsxfem.bordered(whole, vec), S, 3, 7.0))
    want = np.zeros((6, 6))
    want[:3, :3] = K[:3, :3]
    want[3:5, 3:5] = -K[3:5, 3:5] + [[2.0, 0.5], [0.5, 2.0]]
    want[5, 5] = 7.0
    assert np.array_equal(P, want)


def _dense(mat):
    rows, cols, vals = (np.array(t) for t in mat.COO())
    out = np.zeros((mat.height, mat.width))
    np.add.at(out, (rows, cols), vals)
    return out
