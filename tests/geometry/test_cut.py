"""Tests for cutfem.geometry.cut: the discrete surface S_h = {phi_h = 0}, the active mesh and their topology.

Expected values come from exact formulas: sphere area 4 pi R^2 and volume 4/3 pi R^3, torus area
4 pi^2 R r and volume 2 pi^2 R r^2, the area of a plane section of a box, the Euler characteristic
of the surface (2 for a sphere, 0 for a torus, 1 for a disc) and the divergence theorem
(integral of x.n over a closed surface = 3 * enclosed volume).  Convergence rates are fitted by
least squares in log-log scale over at least four spacings.
"""

import numpy as np
import pytest

from cutfem.geometry.cut import CutMesh, cut_mesh
from cutfem.geometry.nodal_values import CutError, snapped_nodal_values
from cutfem.geometry.shapes import Sphere, Torus
from cutfem.geometry.markers import CUT, NEG, POS
from cutfem.geometry.box import structured_box
from cutfem.geometry.mesh import TetMesh
from cutfem.geometry.numbering import TET_FACES
from cutfem.geometry import cut_kernels

# background boxes with binary-exact nodes (spacing 0.25) and the paper's torus box (spacing 0.1)
SPHERE_BOX = structured_box([-2.0] * 3, [2.0] * 3, spacing=0.25)
TORUS_BOX = structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.1)


def fitted_rate(h, err):
    """Least-squares slope of log(err) against log(h)."""
    return np.polyfit(np.log(h), np.log(err), 1)[0]


class PlainFunction:
    """A level set given only by values, no Lipschitz bound (the cut then evaluates every node)."""

    def __init__(self, f):
        self.f = f

    def value(self, x):
        return self.f(np.asarray(x, float))


# ----------------------------------------------------------------------------------------------
# checks shared by many tests
# ----------------------------------------------------------------------------------------------


def piece_centroids(cut):
    """(n, 3) mean of the distinct vertices of each piece (a point inside the convex piece)."""
    V = len(cut.vertices)
    keys = np.unique(cut.triangle_tets[:, None] * V + cut.triangles)
    tet, vert = keys // V, keys % V
    count = np.bincount(tet, minlength=cut.n_tets)
    cent = np.stack([np.bincount(tet, weights=cut.vertices[vert, k], minlength=cut.n_tets) for k in range(3)], axis=1)
    return cent / count[:, None]


def check_closed_surface(cut: CutMesh, chi: int, levelset=None):
    """S_h is closed with Euler characteristic chi, every piece has one owner, normals point out."""
    assert cut.is_closed
    assert cut.euler_characteristic == chi
    # polygonal pieces as faces of a polyhedral surface: V - E + F = chi as well
    assert len(cut.vertices) - len(cut.surface_edges) + cut.n_tets == chi
    # ownership: each triangle has one owner in range, each active tet owns a piece of positive area
    tt = cut.triangle_tets
    assert tt.shape == (cut.n_triangles,) and tt.min() >= 0 and tt.max() < cut.n_tets
    assert np.all(np.bincount(tt, minlength=cut.n_tets) > 0)
    assert len(np.unique(cut.tet_ids)) == cut.n_tets
    assert np.all(cut.triangle_areas > 0)
    assert np.all(cut.piece_areas > 0)
    assert cut.piece_areas.sum() == pytest.approx(cut.area, rel=1e-13)
    # no triangle counted twice (a piece in a face shared by two tets belongs to one of them)
    V = len(cut.vertices)
    tri_keys = np.sort(cut.triangles, axis=1) @ np.array([V * V, V, 1])
    assert len(np.unique(tri_keys)) == cut.n_triangles
    # each triangle lies in its owner tet (barycentric coordinates in [0, 1])
    grads = cut.basis_gradients[tt]  # (T, 4, 3)
    x0 = cut.tet_vertices[tt, 0]  # lambda_k(x) = delta_k0 + grad lambda_k . (x - x0)
    lam = np.einsum("tkd,tvd->tvk", grads, cut.triangle_points - x0[:, None, :])
    lam[:, :, 0] += 1.0
    assert lam.min() > -1e-9 and lam.max() < 1 + 1e-9
    # unit piece normals; triangles oriented by them; outward: int x.n dA = 3 vol > 0
    np.testing.assert_allclose(np.linalg.norm(cut.normals, axis=1), 1.0, rtol=1e-13)
    p = cut.triangle_points
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.all(np.einsum("ij,ij->i", cross, cut.normals[tt]) > 0)
    flux = np.einsum("t,tj,tj->", cut.triangle_areas, p.mean(axis=1), cut.normals[tt])
    assert cut.enclosed_volume > 0
    assert flux == pytest.approx(3 * cut.enclosed_volume, rel=1e-11)
    # conormals are well defined (no zero-length edges)
    assert np.all(cut.surface_edge_lengths > 0)
    assert np.all(np.isfinite(cut.surface_edge_conormals))
    if levelset is not None:
        # vertices lie on edges where phi_h = 0: |phi| <= l^2/8 max|phi''| with l <= sqrt(3) h
        h = np.max(cut.background.spacing)
        assert np.max(np.abs(levelset.value(cut.vertices))) <= 1.5 * h**2


# ----------------------------------------------------------------------------------------------
# convergence of area and volume (rate 2)
# ----------------------------------------------------------------------------------------------

CONVERGENCE_CASES = {
    "sphere": (
        Sphere(1.0, center=(0.013, -0.021, 0.007)),
        ([-1.5] * 3, [1.5] * 3),
        [12, 17, 24, 34],
    ),
    "torus": (
        Torus(1.0, 0.5, center=(0.013, -0.021, 0.007)),
        ([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6]),
        [(16, 16, 6), (24, 24, 9), (32, 32, 12), (48, 48, 18)],
    ),
}
EXACT = {
    "sphere": (4 * np.pi, 4 / 3 * np.pi),
    "torus": (4 * np.pi**2 * 1.0 * 0.5, 2 * np.pi**2 * 1.0 * 0.5**2),
}


@pytest.fixture(scope="module", params=sorted(CONVERGENCE_CASES))
def convergence(request):
    levelset, (lower, upper), cells = CONVERGENCE_CASES[request.param]
    rows = []
    for n in cells:
        box = structured_box(lower, upper, cells=n)
        cut = cut_mesh(box, levelset)
        inside_volume = cut.dx(NEG).quadrature(1).weights.sum()
        rows.append((box.spacing.max(), cut.area, cut.enclosed_volume, inside_volume))
    return request.param, np.array(rows)


def test_area_converges_at_rate_two(convergence):
    name, rows = convergence
    area, _ = EXACT[name]
    h, err = rows[:, 0], np.abs(rows[:, 1] - area)
    assert 1.8 <= fitted_rate(h, err) <= 2.3
    assert err[-1] / area < 5e-3


def test_volume_converges_at_rate_two(convergence):
    name, rows = convergence
    _, volume = EXACT[name]
    h = rows[:, 0]
    for column in (2, 3):  # CutMesh.enclosed_volume, sub-tetrahedra of cut.dx(NEG) + quadrature
        err = np.abs(rows[:, column] - volume)
        assert 1.8 <= fitted_rate(h, err) <= 2.3
        assert err[-1] / volume < 5e-3
    # both compute the volume of the same polyhedron {phi_h < 0}
    np.testing.assert_allclose(rows[:, 2], rows[:, 3], rtol=1e-11)


# ----------------------------------------------------------------------------------------------
# closed surface, Euler characteristic, zero nodal values
# ----------------------------------------------------------------------------------------------


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_sphere_closed_over_random_shifts():
    rng = np.random.default_rng(20240611)
    h = 0.25
    for _ in range(50):
        centre = rng.uniform(-h / 2, h / 2, 3)
        radius = rng.uniform(0.8, 1.5)
        sphere = Sphere(radius, center=centre)
        check_closed_surface(cut_mesh(SPHERE_BOX, sphere), 2, sphere)


@pytest.mark.filterwarnings("error::RuntimeWarning")
@pytest.mark.parametrize("spacing", [0.2, pytest.param(0.1, marks=pytest.mark.slow)])
def test_torus_closed_over_random_shifts(spacing):
    """The paper's box; shifts of up to half a cell in x and y, a quarter cell in z."""
    box = structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=spacing)
    rng = np.random.default_rng(7)
    for _ in range(50):
        shift = rng.uniform(-0.5, 0.5, 3) * spacing * np.array([1.0, 1.0, 0.5])
        torus = Torus(1.0, 0.5, center=shift)
        check_closed_surface(cut_mesh(box, torus), 0, torus)


ZERO_PLACEMENTS = [
    pytest.param(SPHERE_BOX, Sphere(radius, center=centre), 2, id=f"sphere-R{radius}-c{i}")
    for radius in (1.0, 1.25, 1.5)
    for i, centre in enumerate([(0.0, 0.0, 0.0), (0.25, -0.5, 0.25)])
] + [
    pytest.param(TORUS_BOX, Torus(1.0, 0.5, center=centre), 0, id=f"torus-c{i}")
    for i, centre in enumerate([(0.0, 0.0, 0.0), (0.1, -0.1, 0.0)])
]


@pytest.mark.filterwarnings("error::RuntimeWarning")
@pytest.mark.parametrize("box, levelset, chi", ZERO_PLACEMENTS)
def test_closed_with_exact_zero_nodal_values(box, levelset, chi):
    values = levelset.value(box.points)
    zeros = np.flatnonzero(values == 0)
    assert zeros.size > 0  # the placement really puts background nodes on S
    cut = cut_mesh(box, levelset)
    check_closed_surface(cut, chi, levelset)
    # zero rule: a zero node next to an inside node is itself a vertex of S_h
    dist = np.linalg.norm(box.points[zeros][:, None, :] - cut.vertices[None, :, :], axis=2).min(axis=1)
    assert np.sum(dist == 0) > 0


def test_paper_torus_box_has_nodes_that_are_zero_up_to_rounding():
    """Nodes on the torus mathematically with phi = +-1e-16 in floating point must not produce
    zero-length edges or zero-area triangles (they count as zero)."""
    torus = Torus(1.0, 0.5)
    values = torus.value(TORUS_BOX.points)
    assert np.any((values != 0) & (np.abs(values) < 1e-14))
    cut = cut_mesh(TORUS_BOX, torus)
    assert cut.triangle_areas.min() > 1e-14
    assert cut.surface_edge_lengths.min() > 1e-10
    # the public snapped values: exactly those rounding-size values become 0, nothing else moves
    snapped = snapped_nodal_values(TORUS_BOX, torus)
    tiny = np.abs(values) <= 1e-12 * torus.lipschitz * np.linalg.norm(np.subtract(*TORUS_BOX.bounds))
    assert tiny.sum() > np.sum(values == 0)
    np.testing.assert_array_equal(snapped[tiny], 0.0)
    np.testing.assert_array_equal(snapped[~tiny], values[~tiny])


# ----------------------------------------------------------------------------------------------
# the lattice numbering of a structured box and the sorted numbering of a plain TetMesh agree
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "box, levelset",
    [(SPHERE_BOX, Sphere(1.1, center=(0.07, -0.03, 0.11))), (TORUS_BOX, Torus(1.0, 0.5))],
    ids=["sphere", "torus-zeros"],
)
def test_lattice_numbering_equals_the_sorted_numbering(box, levelset):
    """On a structured box the surface vertices are numbered by lattice edges and the interior and
    ghost faces by lattice faces, without sorting node pairs or triples; the plain mesh path sorts
    them.  Both cut every tet in id order here: the arrays must be equal, entry for entry."""
    f = PlainFunction(levelset.value)
    structured, plain = cut_mesh(box, f, check_boundary=False), cut_mesh(TetMesh(box.points, box.tets), f)
    np.testing.assert_array_equal(structured.tet_ids, plain.tet_ids)
    np.testing.assert_array_equal(structured.vertices, plain.vertices)
    np.testing.assert_array_equal(structured.triangles, plain.triangles)
    assert structured.euler_characteristic == plain.euler_characteristic
    for which in (CUT, NEG):
        a, b = structured.interior_facets(which), plain.interior_facets(which)
        assert a.n_facets > 0
        np.testing.assert_array_equal(a.pairs, b.pairs)
        np.testing.assert_array_equal(a.opposite, b.opposite)
    a, b = structured.ghost_facets(NEG), plain.ghost_facets(NEG)
    np.testing.assert_array_equal(a.pairs, b.pairs)
    np.testing.assert_array_equal(a.opposite, b.opposite)


# ----------------------------------------------------------------------------------------------
# active mesh: interior faces; surface edges and conormals
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module", params=["sphere", "torus-zeros"])
def a_cut(request):
    if request.param == "sphere":
        return cut_mesh(SPHERE_BOX, Sphere(1.2, center=(0.03, 0.09, -0.05)))
    return cut_mesh(TORUS_BOX, Torus(1.0, 0.5))


def test_interior_faces(a_cut):
    cut = a_cut
    facets = cut.interior_facets(CUT)
    ft, opp = facets.pairs, facets.opposite
    # the face's local node numbers: those of the first tet without the opposite vertex
    faces = np.take_along_axis(cut.tets[ft[:, 0]], TET_FACES[opp[:, 0]], axis=1)
    np.testing.assert_array_equal(facets.vertices, cut.points[faces])
    assert faces.shape[1] == 3 and ft.shape == (len(faces), 2) and opp.shape == (len(faces), 2)
    assert facets.n_facets == len(faces)
    assert np.all(ft[:, 0] != ft[:, 1])
    for s in range(2):
        tets = cut.tets[ft[:, s]]  # (F, 4)
        # the face's nodes are nodes of the tet, the opposite vertex is not on the face
        assert np.all((faces[:, :, None] == tets[:, None, :]).any(axis=2))
        opposite = tets[np.arange(len(faces)), opp[:, s]]
        assert not np.any(opposite[:, None] == faces)
    # independent count: the faces (sorted node triples) that occur in exactly two active tets
    p = cut.n_nodes
    all_faces = np.sort(cut.tets[:, TET_FACES].reshape(-1, 3), axis=1) @ np.array([p * p, p, 1])
    keys, counts = np.unique(all_faces, return_counts=True)
    assert counts.max() <= 2
    expected = keys[counts == 2]
    got = np.sort(np.sort(faces, axis=1) @ np.array([p * p, p, 1]))
    assert np.array_equal(got, expected)


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_surface_edges_and_conormals(a_cut):
    cut = a_cut
    e, et = cut.surface_edges, cut.surface_edge_tets
    assert np.all(et[:, 0] != et[:, 1])
    # both endpoints are vertices of the pieces of both tets
    V = len(cut.vertices)
    owned = np.unique(cut.triangle_tets[:, None] * V + cut.triangles)
    for s in range(2):
        for k in range(2):
            assert np.all(np.isin(et[:, s] * V + e[:, k], owned))
    # every edge of every piece's triangles that is not a quad diagonal is a surface edge: on a
    # closed surface the number of piece edges is sum over pieces of (3 or 4) / 2
    n_vertices_per_piece = np.bincount(owned // V, minlength=cut.n_tets)
    assert set(np.unique(n_vertices_per_piece)) <= {3, 4}
    assert 2 * len(e) == n_vertices_per_piece.sum()
    # conormals: unit, orthogonal to the edge and to the piece normal, pointing out of the piece
    t = cut.surface_edge_conormals
    d = cut.vertices[e[:, 1]] - cut.vertices[e[:, 0]]
    d /= np.linalg.norm(d, axis=1)[:, None]
    mid = 0.5 * (cut.vertices[e[:, 0]] + cut.vertices[e[:, 1]])
    cent = piece_centroids(cut)
    np.testing.assert_allclose(np.linalg.norm(t, axis=2), 1.0, rtol=1e-12)
    for s in range(2):
        assert np.max(np.abs(np.einsum("ij,ij->i", t[:, s], d))) < 1e-8
        assert np.max(np.abs(np.einsum("ij,ij->i", t[:, s], cut.normals[et[:, s]]))) < 1e-8
        assert np.all(np.einsum("ij,ij->i", t[:, s], mid - cent[et[:, s]]) > 0)
    np.testing.assert_allclose(cut.surface_edge_lengths, np.linalg.norm(cut.vertices[e[:, 1]] - cut.vertices[e[:, 0]], axis=1))


def test_flat_surface_has_opposite_conormals():
    """phi = z - (0.2 x + 0.1 y + 0.05) on [-1, 1]^3: a planar S_h, the graph of the plane over the
    square, of area 4 sqrt(1 + 0.2^2 + 0.1^2); coplanar neighbours have t_{E,K2} = -t_{E,K1}."""
    box = structured_box([-1.0] * 3, [1.0] * 3, cells=6)
    plane = PlainFunction(lambda x: x[..., 2] - (0.2 * x[..., 0] + 0.1 * x[..., 1] + 0.05))
    with pytest.raises(CutError, match="boundary"):
        cut_mesh(box, plane)
    cut = cut_mesh(box, plane, check_boundary=False)
    assert cut.area == pytest.approx(4 * np.sqrt(1 + 0.2**2 + 0.1**2), rel=1e-13)
    normal = np.array([-0.2, -0.1, 1.0]) / np.sqrt(1 + 0.2**2 + 0.1**2)
    np.testing.assert_allclose(cut.normals, np.broadcast_to(normal, cut.normals.shape), atol=1e-13)
    assert not cut.is_closed
    assert cut.euler_characteristic == 1  # a disc
    with pytest.warns(RuntimeWarning, match="not shared by exactly two pieces"):
        t = cut.surface_edge_conormals  # the edges on the box boundary have one piece only
    assert len(t) > 0
    np.testing.assert_allclose(t[:, 0] + t[:, 1], 0.0, atol=1e-12)


# ----------------------------------------------------------------------------------------------
# quadrature on S_h
# ----------------------------------------------------------------------------------------------


def test_surface_quadrature():
    sphere = Sphere(1.3, center=(0.05, -0.02, 0.1))
    cut = cut_mesh(SPHERE_BOX, sphere)
    q = cut.ds().quadrature(2)
    assert q.integrate(np.ones(q.weights.shape)) == pytest.approx(cut.area, rel=1e-13)
    assert np.array_equal(q.parent, cut.triangle_tets)
    np.testing.assert_allclose(q.normal, cut.normals[cut.triangle_tets], rtol=1e-14)
    flux = q.integrate(np.einsum("mqd,md->mq", q.points, q.normal))
    assert flux == pytest.approx(3 * cut.enclosed_volume, rel=1e-12)
    # and S_h is close to S: area and volume within O(h^2) of 4 pi R^2 and 4/3 pi R^3
    assert cut.area == pytest.approx(4 * np.pi * 1.3**2, rel=0.03)
    assert cut.enclosed_volume == pytest.approx(4 / 3 * np.pi * 1.3**3, rel=0.05)

    def quadratic(x):
        return x[..., 0] ** 2 - 2 * x[..., 1] * x[..., 2] + 3 * x[..., 2] + 0.5

    q8 = cut.ds().quadrature(8)
    assert q.integrate(quadratic(q.points)) == pytest.approx(q8.integrate(quadratic(q8.points)), rel=1e-12)
    # per piece as well
    per2 = np.bincount(q.parent, weights=q.integrate_per_element(quadratic(q.points)), minlength=cut.n_tets)
    per8 = np.bincount(q8.parent, weights=q8.integrate_per_element(quadratic(q8.points)), minlength=cut.n_tets)
    np.testing.assert_allclose(per2, per8, rtol=1e-11, atol=1e-15)


# ----------------------------------------------------------------------------------------------
# bad input
# ----------------------------------------------------------------------------------------------


def test_cut_error_is_a_value_error():
    assert issubclass(CutError, ValueError)


@pytest.mark.parametrize(
    "levelset",
    [Sphere(0.5, center=(10.0, 0.0, 0.0)), Sphere(0.05, center=(0.125, 0.125, 0.125))],
    ids=["far-outside", "tiny-between-nodes"],
)
def test_level_set_that_does_not_cut(levelset):
    with pytest.raises(CutError, match="does not cut"):
        cut_mesh(SPHERE_BOX, levelset)
    with pytest.raises(CutError, match="does not cut"):
        cut_mesh(TetMesh(SPHERE_BOX.points, SPHERE_BOX.tets), levelset)


@pytest.mark.parametrize(
    "levelset", [Sphere(2.5), Sphere(1.0, center=(1.5, 0.0, 0.0))], ids=["bigger-than-box", "crossing-a-side"]
)
def test_surface_reaching_the_box_boundary(levelset):
    """The structured box decides after its band search (one node when the band stays off the
    faces, every boundary node otherwise): the same error, with the same count of boundary nodes
    inside, as the plain mesh's check of every boundary node."""
    with pytest.raises(CutError, match="boundary nodes.*Enlarge the box") as structured:
        cut_mesh(SPHERE_BOX, levelset)
    with pytest.raises(CutError, match="boundary nodes") as plain:
        cut_mesh(TetMesh(SPHERE_BOX.points, SPHERE_BOX.tets), levelset)
    assert str(structured.value).split(" boundary")[0] == str(plain.value).split(" boundary")[0]


def test_background_with_a_hole_inside_the_surface_names_the_hole():
    """A background mesh with a cavity inside the surface (tets removed around the centre of the
    ball) has boundary nodes inside; the surface does not leave the box, so the error names the
    hole rather than asking for a larger box."""
    box = structured_box([-1.0] * 3, [1.0] * 3, cells=8)
    centres = box.points[box.tets].mean(axis=1)
    holed = TetMesh(box.points, box.tets[np.linalg.norm(centres, axis=1) > 0.3])
    with pytest.raises(CutError, match=r"off the faces of the mesh's bounding box.*hole") as err:
        cut_mesh(holed, Sphere(0.6))
    assert "Enlarge the box" not in str(err.value)


def test_stray_points_do_not_move_the_box_of_the_boundary_checks():
    """A point that no tet uses, far off the mesh, is not part of the background's box: the surface
    that leaves the box [-1, 1]^3 is still told to enlarge it, not to look for a hole."""
    box = structured_box([-1.0] * 3, [1.0] * 3, cells=8)
    stray = TetMesh(np.vstack([box.points, [[50.0, -7.0, 3.0]]]), box.tets)
    with pytest.raises(CutError, match=r"surface reaches or leaves the box \[\[-1.0, -1.0, -1.0\], \[1.0, 1.0, 1.0\]\]"):
        cut_mesh(stray, Sphere(1.3))


def test_level_set_is_not_needed_at_points_that_no_tet_uses():
    """A level set that is NaN at a stray point of the background (used by no tet, far off the box)
    rejected the mesh.  The level set is evaluated at the nodes of the tets only: the cut equals the
    one without the stray point (same node ids: the point comes last), bit for bit, and the sides
    are found; a NaN at a node of a tet is still refused."""
    box = structured_box([-1.0] * 3, [1.0] * 3, cells=8)
    plain = TetMesh(box.points, box.tets)
    stray = TetMesh(np.vstack([box.points, [[50.0, -7.0, 3.0]]]), box.tets)

    def f(x):
        r = np.linalg.norm(x, axis=-1)
        return np.where(r > 10, np.nan, r - 0.6)

    reference, cut = cut_mesh(plain, f), cut_mesh(stray, f)
    assert cut.area == reference.area and np.array_equal(cut.triangles, reference.triangles)
    assert cut.dx(NEG).size == reference.dx(NEG).size
    values = snapped_nodal_values(stray, f)
    assert np.array_equal(values[:-1], snapped_nodal_values(plain, f)) and np.isnan(values[-1])
    nodal = np.append(snapped_nodal_values(plain, f), np.nan)  # nodal values given as an array
    assert cut_mesh(stray, nodal).area == reference.area
    nodal[0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        cut_mesh(stray, nodal)


@pytest.mark.parametrize("scale, offset", [(1.0, (1e4, -2e4, 3e4)), (1e3, (1e4, -2e4, 3e4)), (1e-3, (10.0, -20.0, 30.0))])
def test_cut_of_a_moved_and_scaled_mesh_scales_exactly(scale, offset):
    """A mesh in other units far from the origin (x -> scale x + offset) with the moved sphere: the
    nodal values are the same up to the factor scale, so S_h is the same surface moved and scaled,
    its area times scale**2, the volumes of the sides times scale**3, to round-off of the moved
    coordinates (1e-16 * 3.7e4 / spacing 0.25 relative).  CutMesh.enclosed_volume summed
    x . (y x z) from the origin: 0.8286 for 0.8256 at the offset 1e4 in the same units, 0.8223 at
    the offset 10 in 1e-3 units."""
    box = structured_box([-1.0] * 3, [1.0] * 3, cells=8)
    pts = box.points.copy()
    inner = np.all(np.abs(pts) < 1 - 1e-9, axis=1)
    pts[inner] += np.random.default_rng(0).uniform(-0.025, 0.025, (inner.sum(), 3))
    offset, centre = np.asarray(offset), np.array([0.1, 0.05, -0.02])
    reference = cut_mesh(TetMesh(pts, box.tets), Sphere(0.6, centre))
    moved = cut_mesh(TetMesh(scale * pts + offset, box.tets), Sphere(0.6 * scale, scale * centre + offset))
    assert moved.n_triangles == reference.n_triangles
    assert moved.area / scale**2 == pytest.approx(reference.area, rel=1e-10)
    assert moved.enclosed_volume / scale**3 == pytest.approx(reference.enclosed_volume, rel=1e-10)
    assert moved.dx(NEG).size / scale**3 == pytest.approx(reference.dx(NEG).size, rel=1e-10)
    assert moved.dx(POS).size / scale**3 == pytest.approx(8.0 - reference.dx(NEG).size, rel=1e-10)


def test_nan_values():
    def f(x):
        x = np.asarray(x, float)
        r = np.linalg.norm(x, axis=-1) - 1.0
        return np.where(x[..., 0] > 0.9, np.nan, r)  # NaN on part of the surface

    class BandNaN:
        lipschitz = 1.0

        def value(self, x):
            return f(x)

    for box in (SPHERE_BOX, TetMesh(SPHERE_BOX.points, SPHERE_BOX.tets)):
        for levelset in (f, BandNaN()):
            with pytest.raises(ValueError, match="NaN"):
                cut_mesh(box, levelset)
    with pytest.raises(ValueError, match="NaN"):  # the nodal values behind the sides of a cut
        snapped_nodal_values(SPHERE_BOX, f)
    values = Sphere(1.0).value(SPHERE_BOX.points)
    values[17] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        cut_mesh(SPHERE_BOX, values)


# ----------------------------------------------------------------------------------------------
# the orientation of the triangles by the sign table
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(4))
def test_sign_table_orientation_equals_the_determinant(seed):
    """Random nodal values (a tenth of them exactly zero) on a perturbed mesh with a few tets
    given in negative orientation: every triangle of S_h turns counterclockwise about n_h, as
    the determinant (x_1 - x_0) x (x_2 - x_0) . n_h says (checked where it is not rounding)."""
    rng = np.random.default_rng(seed)
    box = structured_box([0, 0, 0], [1, 1, 1], cells=6)
    pts = box.points + rng.uniform(-0.03, 0.03, box.points.shape) * (np.abs(box.points - 0.5) < 0.49).all(1)[:, None]
    tets = box.tets.copy()
    swap = rng.random(len(tets)) < 0.3
    tets[swap, 2], tets[swap, 3] = tets[swap, 3], tets[swap, 2].copy()  # negative orientation
    mesh = TetMesh(pts, tets, check=False)
    values = rng.standard_normal(len(pts)) + 0.3
    values[rng.random(len(pts)) < 0.1] = 0.0
    boundary = (np.abs(pts - 0.5) > 0.49).any(axis=1)
    values[boundary] = np.abs(values[boundary]) + 0.1  # outside on the boundary
    cut = cut_mesh(mesh, values)
    p = cut.triangle_points
    det = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), cut.normals[cut.triangle_tets])
    scale = np.linalg.norm(p[:, 1] - p[:, 0], axis=1) * np.linalg.norm(p[:, 2] - p[:, 0], axis=1)
    clear = np.abs(det) > 1e-10 * scale
    assert clear.sum() > 0.99 * len(det) and len(det) > 100
    assert np.all(det[clear] > 0)


def test_marching_codes_collapsed_pieces_and_slot_keys_against_the_case_table():
    """The compiled marching pass and slot keys against a plain reading of the case table: sign
    code, the tets kept (at least three distinct vertices, a slot being the node j when
    phi_j == 0 and its edge (i, j) otherwise) compacted in order, and the slot keys (node j, or
    p + min p + max of the edge's nodes); values drawn with many exact zeros."""
    from cutfem.geometry.cut import _marching
    from cutfem.geometry.marching import CASES, EDGE_I, EDGE_J
    from cutfem.geometry.cut_kernels import slot_keys

    rng = np.random.default_rng(11)
    vals = rng.choice([-1.0, 0.0, 0.5, -0.25, 2.0], size=(3000, 4))
    vals = vals[np.any(vals < 0, axis=1) & np.any(vals >= 0, axis=1)]  # tets with both signs
    p = 50
    labels = rng.integers(0, p, size=(len(vals), 4))
    ids = np.arange(len(vals)) * 7
    kept, expected_codes, expected_keys = [], [], []
    for t, v in enumerate(vals):
        c = sum(1 << k for k in range(4) if v[k] < 0)
        edges = CASES[c] + CASES[c][-1:] * (4 - len(CASES[c]))
        vertices = {("node", j) if v[j] == 0 else ("edge", i, j) for i, j in edges}
        if len(vertices) >= 3:
            kept.append(t)
            expected_codes.append(c)
            a, b = labels[t, [i for i, _ in edges]], labels[t, [j for _, j in edges]]
            zero = v[[j for _, j in edges]] == 0
            expected_keys.append(np.where(zero, b, p + np.minimum(a, b) * p + np.maximum(a, b)))
    orig_vals, orig_labels = vals.copy(), labels.copy()
    tet_ids, lab, val, code = _marching(ids.copy(), labels.copy(), vals.copy())
    assert 0 < len(kept) < len(vals)  # both kinds occur
    np.testing.assert_array_equal(tet_ids, ids[kept])
    np.testing.assert_array_equal(lab, orig_labels[kept])
    np.testing.assert_array_equal(val, orig_vals[kept])
    np.testing.assert_array_equal(code, expected_codes)
    np.testing.assert_array_equal(slot_keys(lab, code, val, EDGE_I, EDGE_J, p), expected_keys)


def test_edge_census_against_a_sort_of_the_edge_keys():
    """cut_kernels.edge_census (half-edges bucketed by their lower vertex) against np.unique of the keys
    min V + max: the same number of edges and of edges not in two triangles, on S_h of a cut torus
    (closed: none) and on hand examples."""

    cut = cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.1), Torus())
    t, V = cut.triangles, len(cut.vertices)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]).astype(np.int64)
    _, reference = np.unique(np.minimum(e[:, 0], e[:, 1]) * V + np.maximum(e[:, 0], e[:, 1]), return_counts=True)
    assert cut_kernels.edge_census(t, V) == (len(reference), int(np.sum(reference != 2))) == (len(reference), 0)
    assert cut.is_closed and cut.euler_characteristic == 0
    # two triangles on the edge {1, 2} and a third on {2, 3} again: edges 01 02 12 13 23 24 34 with
    # counts 1 1 2 1 2 1 1
    tri = np.array([[0, 1, 2], [3, 2, 1], [4, 3, 2]])
    assert cut_kernels.edge_census(tri, 5) == (7, 5)
    # the surface of a tetrahedron: 6 edges, each in two triangles
    assert cut_kernels.edge_census(np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [0, 2, 3]], dtype=np.int32), 4) == (6, 0)
    assert cut_kernels.edge_census(np.empty((0, 3), dtype=np.int64), 0) == (0, 0)


def test_element_set_volumes_on_a_box_and_on_a_tet_mesh():
    """On a structured box every tet has the box's tet volume, built on access (volumes_of for a
    slice, indices or a mask gives the same as indexing the whole array); on a tet mesh the volumes
    are the stored |det| / 6 of each tet; the cut tets' volumes agree with both."""
    box = structured_box([-1.2] * 3, [1.2] * 3, spacing=0.2)
    cut = cut_mesh(box, Sphere(1.0))
    for which in (CUT, NEG):
        es = cut.elements(which)
        v = es.volumes
        assert v.shape == (es.n_elements,) and v.flags.writeable and np.all(v == box.tet_volume)
        mask = np.arange(es.n_elements) % 3 == 0
        for idx in (slice(5, 40), np.array([7, 2, 7, es.n_elements - 1]), mask):
            np.testing.assert_array_equal(es.volumes_of(idx), v[idx])
    np.testing.assert_allclose(box.tet_volume, np.prod(box.spacing) / 6, rtol=1e-15)
    mesh = TetMesh(box.points, box.tets)
    plain = cut_mesh(mesh, Sphere(1.0))
    es = plain.elements(CUT)
    X = es.points[es.tets]
    np.testing.assert_allclose(es.volumes, np.abs(np.linalg.det(X[:, 1:] - X[:, :1])) / 6, rtol=1e-12)
    np.testing.assert_allclose(es.volumes_of(slice(3, 9)), es.volumes[3:9], rtol=0)
    np.testing.assert_allclose(plain.tet_volumes.sum(), cut.tet_volumes.sum(), rtol=1e-12)

