"""Tests of the cut by several level sets (cutfem.geometry.csg, csg_cut, csg_kernels).

Expected values are exact: a cube of six planes is reproduced to round-off (P1 is exact for planes,
on the grid's planes or across them); a ball cut by the plane z = c has the volume
4/3 pi R^3 - pi d^2 (3R - d) / 3 (d = R - c the cap's height), the flat disc the area pi (R^2 - c^2)
and the sphere part 4 pi R^2 - 2 pi R d, approached at rate 2 (P1 interpolation of the sphere); a cube
minus a ball the difference of their volumes.  Every cut is also checked against identities: the
sub-tets of a clipped tet fill it (|T ∩ NEG| + |T ∩ POS| = |T|), the divergence theorem
(1/3) int x.n = |Omega_h| on the closed, outward-oriented boundary, the parts' areas sum to the
boundary's.
"""

import numpy as np
import pytest

import cutfem as cf
from cutfem.geometry.csg import MAX_LEVELSETS, Domain, complement, difference, intersection, union
from cutfem.geometry.csg_cut import CsgCut, _check_closed_boundary
from cutfem.geometry.mesh import TetMesh
from cutfem.geometry.nodal_values import CutError
from cutfem.geometry.quadrature import signed_volumes
from cutfem.geometry.shapes import Plane, Sphere


def fitted_rate(h, err):
    return np.polyfit(np.log(h), np.log(err), 1)[0]


def cube(a, center=(0.0, 0.0, 0.0), rotation=np.eye(3)):
    """The six half-spaces of the cube |x - c|_inf < a in the frame of ``rotation``'s columns."""
    c = np.asarray(center, float)
    return [Plane(s * rotation[:, k], c + s * a * rotation[:, k]) for k in range(3) for s in (1.0, -1.0)]


def rotation(angles):
    (a, b, g) = angles
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rx = np.array([[1, 0, 0], [0, np.cos(g), -np.sin(g)], [0, np.sin(g), np.cos(g)]])
    return rz @ ry @ rx


def check_identities(cut: CsgCut, box_volume: float):
    """The sides fill the box, each clipped tet is filled by its sub-tets, the boundary is closed and
    outward (divergence theorem), the triangles turn counterclockwise about their normals, and the
    parts' areas sum to the boundary's."""
    neg, pos = cut.dx(cf.NEG).size, cut.dx(cf.POS).size
    assert neg + pos == pytest.approx(box_volume, rel=1e-13)
    volumes = np.abs(signed_volumes(cut.sub_tets))
    per_tet = np.bincount(cut.sub_parent, weights=volumes, minlength=len(cut.clipped))
    bg = cut.background
    tet_volume = bg.tet_volume if hasattr(bg, "tet_volume") else bg.volumes[cut.clipped]
    clipped = cut.state[cut.clipped] == -1
    np.testing.assert_allclose(per_tet[clipped], np.broadcast_to(tet_volume, per_tet.shape)[clipped], rtol=1e-12)
    p = cut.vertices[cut.triangles]
    assert np.einsum("ij,ij->", p[:, 0], np.cross(p[:, 1], p[:, 2])) / 6 == pytest.approx(neg, rel=1e-12, abs=1e-13)
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.all(np.einsum("ij,ij->i", cross, cut.triangle_normals) > 0)
    np.testing.assert_allclose(np.linalg.norm(cut.triangle_normals, axis=1), 1.0, rtol=1e-14)
    assert sum(cut.part_area(k) for k in range(len(cut.levelsets))) == pytest.approx(cut.area, rel=1e-13)
    assert cut.ds().size == pytest.approx(cut.area, rel=1e-13)


# ----------------------------------------------------------------------------------------------
# the domain algebra
# ----------------------------------------------------------------------------------------------


def test_tables_of_the_boolean_combinations():
    a, b, c = Sphere(1.0), Plane(), Plane((1, 0, 0))
    # bit k of the code: phi_k < 0 (inside level set k)
    np.testing.assert_array_equal(intersection(a, b).table(), [False, False, False, True])
    np.testing.assert_array_equal(union(a, b).table(), [False, True, True, True])
    np.testing.assert_array_equal(difference(a, b).table(), [False, True, False, False])
    np.testing.assert_array_equal(complement(a).table(), [True, False])
    d = union(intersection(a, b), difference(c, a))  # a nested domain: a appears twice, counted once
    assert d.levelsets == (a, b, c) and d.names == ("phi1", "phi2", "phi3")
    codes = np.arange(8)
    inside = [(codes >> k) & 1 == 1 for k in range(3)]
    np.testing.assert_array_equal(d.table(), (inside[0] & inside[1]) | (inside[2] & ~inside[0]))
    assert str(d) == "(phi1 & phi2) | (phi3 & ~phi1)"
    assert d.index(c) == d.index(2) == d.index("phi3") == 2


def test_text_domains_number_their_level_sets_as_given():
    a, b, c = Sphere(1.0), Plane(), Plane((1, 0, 0))
    d = Domain.from_text("phi2 - (phi1 | ~phi3)", [a, b, c])
    assert d.levelsets == (a, b, c)
    codes = np.arange(8)
    inside = [(codes >> k) & 1 == 1 for k in range(3)]
    np.testing.assert_array_equal(d.table(), inside[1] & ~(inside[0] | ~inside[2]))


@pytest.mark.parametrize("text, message", [
    ("phi1 & phi3", r"names 'phi3', which is not one of its level sets: use phi1, phi2"),
    ("phi1 + phi2", r"holds 'phi1 \+ phi2'; a domain is written with the names phi1, phi2, & \(intersection\)"),
    ("max(phi1, phi2)", r"holds 'max\(phi1, phi2\)'"),
    ("phi1 &", r"is not an expression of"),
    ("phi1", r"does not use phi2"),
])
def test_a_text_domain_that_is_not_one_is_refused(text, message):
    with pytest.raises(ValueError, match=message):
        Domain.from_text(text, [Sphere(1.0), Plane()])


def test_parts_that_are_not_level_sets_and_too_many_level_sets_are_refused():
    with pytest.raises(TypeError, match="a part of a domain is a Domain or a level set"):
        intersection(Sphere(1.0), "sphere")
    with pytest.raises(ValueError, match=f"at most {MAX_LEVELSETS} level sets"):
        intersection(*[Plane((1, 0, 0), (k / 100, 0, 0)) for k in range(MAX_LEVELSETS + 1)])
    with pytest.raises(ValueError, match=r"is not a level set of the domain phi1 & phi2: give one of its level sets, its "
                                         r"number 0..1 or its name \(phi1, phi2\)"):
        intersection(Sphere(1.0), Plane()).index("phi3")


def test_bounds_of_a_domain_from_its_bounded_level_sets():
    ball, cap = Sphere(1.0, (0.5, 0, 0)), Plane()
    lo, hi = intersection(ball, cap).bounds()
    np.testing.assert_array_equal(lo, [-0.5, -1, -1])
    np.testing.assert_array_equal(hi, [1.5, 1, 1])
    assert union(ball, cap).bounds() is None and complement(ball).bounds() is None
    lo, hi = union(ball, Sphere(1.0, (-0.5, 0, 0))).bounds()
    np.testing.assert_array_equal(lo, [-1.5, -1, -1])


# ----------------------------------------------------------------------------------------------
# exact domains
# ----------------------------------------------------------------------------------------------

BOX = cf.structured_box([-1.25] * 3, [1.25] * 3, spacing=0.25)


@pytest.mark.parametrize("a, rot", [(0.5, None), (0.43, None), (0.55, (0.3, 0.5, 0.7))], ids=["on-grid", "off-grid", "rotated"])
def test_a_cube_of_six_planes_is_exact(a, rot):
    """The cube of six half-spaces: volume (2a)^3 and six faces of area (2a)^2 to round-off, on the
    grid's planes (nodes with phi = 0: the zero rule), across them and rotated against the grid."""
    cut = cf.cut_mesh(BOX, intersection(*cube(a, rotation=np.eye(3) if rot is None else rotation(rot))))
    assert cut.dx(cf.NEG).size == pytest.approx((2 * a) ** 3, rel=1e-13)
    for k in range(6):
        assert cut.part_area(k) == pytest.approx((2 * a) ** 2, rel=1e-13)
        n = cut.triangle_normals[cut.triangle_parts == k]
        np.testing.assert_allclose(n, np.broadcast_to(cut.levelsets[k].normal_vector, n.shape), atol=1e-13)
    check_identities(cut, 2.5**3)


def test_a_cube_on_an_unstructured_mesh_is_exact():
    box = BOX
    rng = np.random.default_rng(1)
    points = box.points.copy()
    inner = np.all(np.abs(points) < 1.2, axis=1)
    points[inner] += rng.uniform(-0.06, 0.06, (int(inner.sum()), 3))
    mesh = TetMesh(points, box.tets)
    cut = cf.cut_mesh(mesh, intersection(*cube(0.5, (0.05, -0.1, 0.02))))
    assert cut.dx(cf.NEG).size == pytest.approx(1.0, rel=1e-13)
    assert [cut.part_area(k) for k in range(6)] == pytest.approx([1.0] * 6, rel=1e-13)
    check_identities(cut, 2.5**3)


def test_one_level_set_as_a_domain_is_the_cut_by_it():
    """intersection(ball) clips by one plane per tet: the same volume, boundary area and sets as
    cut_mesh(box, ball) (its pieces, triangle for triangle)."""
    ball = Sphere(0.8, (0.03, 0.0, -0.02))
    one, csg = cf.cut_mesh(BOX, ball), cf.cut_mesh(BOX, intersection(ball))
    assert csg.dx(cf.NEG).size == pytest.approx(one.dx(cf.NEG).size, rel=1e-14)
    assert csg.dx(cf.POS).size == pytest.approx(one.dx(cf.POS).size, rel=1e-14)
    assert csg.area == pytest.approx(one.area, rel=1e-14) and csg.n_triangles == one.n_triangles
    for which in (cf.CUT, cf.NEG, cf.POS):
        np.testing.assert_array_equal(csg.elements(which).tet_ids, one.elements(which).tet_ids)
    assert csg.ghost_facets(cf.NEG).n_facets == one.ghost_facets(cf.NEG).n_facets


def ball_and_plane(R, c):
    d = R - c  # the height of the cap above the plane z = c
    return {"volume": 4 / 3 * np.pi * R**3 - np.pi * d**2 * (3 * R - d) / 3, "disc": np.pi * (R**2 - c**2),
            "sphere": 4 * np.pi * R**2 - 2 * np.pi * R * d}


def test_a_ball_cut_by_a_plane_converges_at_rate_two():
    """Ball (R = 1) below z = 0.4: volume, disc and sphere part at rate 2 (0.4 to 0.05); the disc's
    normal is exactly (0, 0, 1), the sphere part's within O(h) of x / |x|."""
    ball, cap = Sphere(1.0), Plane((0, 0, 1), (0, 0, 0.4))
    exact = ball_and_plane(1.0, 0.4)
    h, errors = [], {k: [] for k in exact}
    for s in (0.4, 0.2, 0.1, 0.05):
        cut = cf.cut_mesh(cf.structured_box([-1.2] * 3, [1.2] * 3, spacing=s), intersection(ball, cap))
        h.append(cut.h)
        got = {"volume": cut.dx(cf.NEG).size, "disc": cut.part_area(cap), "sphere": cut.part_area(ball)}
        for k in exact:
            errors[k].append(abs(got[k] - exact[k]))
        disc = cut.triangle_parts == 1
        np.testing.assert_allclose(cut.triangle_normals[disc], np.broadcast_to([0.0, 0, 1], (int(disc.sum()), 3)), atol=1e-14)
        centroids = cut.vertices[cut.triangles[~disc]].mean(axis=1)
        radial = np.einsum("ij,ij->i", cut.triangle_normals[~disc], centroids / np.linalg.norm(centroids, axis=1)[:, None])
        assert radial.min() > 1 - 2 * s**2
        check_identities(cut, 2.4**3)
    # measured: fitted rates 2.13 (volume), 2.15 (disc), 2.15 (sphere part); at spacing 0.05 the
    # errors 3.7e-3, 1.5e-3, 5.1e-3
    for k in exact:
        assert fitted_rate(h, errors[k]) > 1.9, (k, errors[k])
    assert errors["volume"][-1] < 4e-3 and errors["disc"][-1] < 1.7e-3


def test_a_cube_minus_a_ball_through_a_face():
    """The cube |x|_inf < 0.7 minus the ball of radius 0.4 about the centre of its face x = 0.7: a
    half ball removed, the face with a disc missing, the sphere part a half sphere (rate 2)."""
    ball = Sphere(0.4, (0.7, 0.0, 0.0))
    r = 0.4
    exact = {"volume": 1.4**3 - 2 / 3 * np.pi * r**3, "face": 1.4**2 - np.pi * r**2, "sphere": 2 * np.pi * r**2}
    h, errors = [], {k: [] for k in exact}
    planes = cube(0.7, rotation=rotation((0.0, 0.0, 0.0)))
    for s in (0.2, 0.1, 0.05):
        box = cf.structured_box([-1.0] * 3, [1.0] * 3, spacing=s)
        cut = cf.cut_mesh(box, difference(intersection(*planes), ball))
        h.append(cut.h)
        got = {"volume": cut.dx(cf.NEG).size, "face": cut.part_area(planes[0]), "sphere": cut.part_area(ball)}
        for k in exact:
            errors[k].append(abs(got[k] - exact[k]))
        for k in range(1, 6):
            assert cut.part_area(planes[k]) == pytest.approx(1.4**2, rel=1e-12)
        check_identities(cut, 8.0)
        # the sphere part's normal points into the ball: out of the domain
        on_ball = cut.triangle_parts == 6
        centroids = cut.vertices[cut.triangles[on_ball]].mean(axis=1) - ball.center
        assert np.all(np.einsum("ij,ij->i", cut.triangle_normals[on_ball], centroids) < 0)
    # measured: fitted rates 2.11 (volume), 2.82 (face), 2.13 (half sphere)
    for k in exact:
        assert fitted_rate(h, errors[k]) > 1.9, (k, errors[k])


@pytest.mark.parametrize("seed", range(4))
def test_random_combinations_close_and_fill_the_box(seed):
    """Unions, differences and the symmetric difference of random balls and planes: closed,
    outward, and their sides fill the box (a union's boundary may have edges in four triangles)."""
    rng = np.random.default_rng(seed)
    box = cf.structured_box([-1.5] * 3, [1.5] * 3, spacing=0.2)
    c = rng.uniform(-0.2, 0.2, 3)
    ball, ball2 = Sphere(rng.uniform(0.7, 1.0), c), Sphere(rng.uniform(0.3, 0.6), c + rng.uniform(-0.5, 0.5, 3))
    plane, plane2 = Plane(rng.normal(size=3), c + rng.uniform(-0.2, 0.2, 3)), Plane(rng.normal(size=3), c)
    domains = [union(intersection(ball, plane), ball2), intersection(ball, plane, complement(plane2)),
               union(intersection(ball, plane, ball2), intersection(ball, complement(plane), complement(ball2)))]
    for domain in domains:
        check_identities(cf.cut_mesh(box, domain), 27.0)


def test_element_sets_facets_and_a_field_on_the_domain():
    ball, cap = Sphere(1.0), Plane((0, 0, 1), (0, 0, 0.4))
    cut = cf.cut_mesh(cf.structured_box([-1.2] * 3, [1.2] * 3, spacing=0.2), intersection(ball, cap))
    neg, pos, cuts = (cut.elements(w) for w in (cf.NEG, cf.POS, cf.CUT))
    assert np.all(neg.contains(cuts.tet_ids)) and np.all(pos.contains(cuts.tet_ids))
    both = np.intersect1d(neg.tet_ids, pos.tet_ids)
    np.testing.assert_array_equal(both, cuts.tet_ids)  # the cut tets, and only they, are on both sides
    ghost = cut.ghost_facets(cf.NEG)
    assert ghost.n_facets > 0 and np.all(cuts.contains(neg.tet_ids[ghost.pairs]).any(axis=1))
    V = cf.CutSpace(cut, cf.NEG)
    # the stiffness of a linear function is its energy over Omega_h: |grad u|^2 |Omega_h|
    u = V.dof_points @ np.array([1.0, 2.0, -0.5])
    K = cf.assemble(cf.stiffness(cut.dx(cf.NEG)), V)
    assert u @ K @ u == pytest.approx(5.25 * cut.dx(cf.NEG).size, rel=1e-12)


# ----------------------------------------------------------------------------------------------
# boundary parts: ds(part, where=...)
# ----------------------------------------------------------------------------------------------


def test_boundary_parts_by_level_set_number_and_name():
    ball, cap = Sphere(1.0), Plane((0, 0, 1), (0, 0, 0.4))
    cut = cf.cut_mesh(cf.structured_box([-1.2] * 3, [1.2] * 3, spacing=0.2), intersection(ball, cap))
    assert cut.ds(cap) is cut.ds(1) and cut.ds("phi2").size == cut.part_area(1)
    assert cut.ds([0, 1]).size == pytest.approx(cut.area, rel=1e-14)
    assert cut.ds(0).size + cut.ds(1).size == pytest.approx(cut.ds().size, rel=1e-14)
    q = cut.ds(cap).quadrature(2)
    np.testing.assert_allclose(q.normal, np.broadcast_to([0.0, 0, 1], q.normal.shape), atol=1e-14)
    with pytest.raises(ValueError, match=r"is not a level set of the domain"):
        cut.ds(Plane())
    with pytest.raises(ValueError, match=r"ds\(\[\]\) names no part"):
        cut.ds([])
    # the built-in Nitsche term is exact on S_h of one level set (one normal per tet): a part is refused
    with pytest.raises(TypeError, match=r"nitsche integrates over a SurfacePieces measure, got BoundaryPart\('Gamma_h on phi1'\)"):
        cf.nitsche(cut.ds(ball))


def test_a_part_of_the_sphere_tagged_by_a_plane():
    """cut.ds(where=plane) of the one-level-set cut: the part of S_h below z = c, clipped exactly; it
    and its complement share S_h's area to round-off, and the tagged area converges at rate 2 to the
    spherical cap's 2 pi R (R + c)."""
    ball, R, c = Sphere(1.0), 1.0, 0.3
    plane = Plane((0, 0, 1), (0, 0, c))
    h, err = [], []
    for s in (0.4, 0.2, 0.1, 0.05):
        cut = cf.cut_mesh(cf.structured_box([-1.2] * 3, [1.2] * 3, spacing=s), ball)
        below, above = cut.ds(where=plane), cut.ds(where=complement(plane))
        assert below.size + above.size == pytest.approx(cut.area, rel=1e-13)
        q = below.quadrature(2)
        assert np.all(q.points[..., 2] <= c + 1e-14) and np.all(above.quadrature(2).points[..., 2] >= c - 1e-14)
        np.testing.assert_allclose(q.normal, cut.normals[q.parent], rtol=1e-14)
        h.append(cut.h)
        err.append(abs(below.size - 2 * np.pi * R * (R + c)))
    assert fitted_rate(h, err) > 1.8, err


def test_a_part_of_a_csg_boundary_tagged_by_another_domain():
    ball, cap = Sphere(1.0), Plane((0, 0, 1), (0, 0, 0.4))
    cut = cf.cut_mesh(cf.structured_box([-1.2] * 3, [1.2] * 3, spacing=0.1), intersection(ball, cap))
    side = Plane((1, 0, 0), (0.2, 0, 0))
    band = intersection(side, complement(Plane((1, 0, 0), (-0.3, 0, 0))))  # -0.3 < x < 0.2
    parts = [cut.ds(cap, where=band), cut.ds(cap, where=complement(band))]
    assert parts[0].size + parts[1].size == pytest.approx(cut.part_area(cap), rel=1e-13)
    # the disc of radius sqrt(1 - 0.16) in the band -0.3 < x < 0.2, against the polygon's: within 1e-2
    r = np.sqrt(1 - 0.16)
    seg = lambda x: r**2 * np.arcsin(x / r) + x * np.sqrt(r**2 - x**2)  # noqa: E731: 2 * the area left of x
    assert parts[0].size == pytest.approx(seg(0.2) - seg(-0.3), abs=1e-2)


# ----------------------------------------------------------------------------------------------
# refusals
# ----------------------------------------------------------------------------------------------


def test_a_level_set_that_misses_the_box_is_refused():
    with pytest.raises(CutError, match=r"level set phi2 of the domain \(Plane\(.*\)\) does not cut the background mesh: it is "
                                       r"negative at every node"):
        cf.cut_mesh(BOX, intersection(Sphere(1.0), Plane((0, 0, 1), (0, 0, 5.0))))


def test_nan_values_name_the_level_set():
    def bad(x):
        return np.where(x[..., 0] > 0.5, np.nan, x[..., 2])

    with pytest.raises(ValueError, match=r"level set phi2 of the domain .*NaN or infinite values"):
        cf.cut_mesh(BOX, intersection(Sphere(1.0), bad))


def test_a_domain_reaching_the_box_or_empty_is_refused():
    with pytest.raises(CutError, match=r"boundary nodes of the background mesh lie in the domain phi1 \| phi2"):
        cf.cut_mesh(BOX, union(Sphere(1.0), Plane()))
    with pytest.raises(CutError, match=r"has no boundary inside the background mesh: Omega_h is empty"):
        cf.cut_mesh(BOX, intersection(Sphere(0.4, (-0.6, 0, 0)), Sphere(0.4, (0.6, 0, 0))))
    # without the check, a half ball leaving the box is cut, its boundary open on the box's faces
    cut = cf.cut_mesh(BOX, union(Sphere(1.0), Plane()), check_boundary=False)
    assert cut.dx(cf.NEG).size == pytest.approx(2.5**3 / 2 + 2 * np.pi / 3, rel=0.02)


def test_an_open_boundary_is_refused():
    cut = cf.cut_mesh(BOX, intersection(*cube(0.43)))
    with pytest.raises(CutError, match=r"the boundary of the domain .* is not closed: 3 edges of its triangles are run through"):
        _check_closed_boundary(cut.vertices, cut.triangles[1:], cut.background, True, cut.domain)


def test_eight_planes_in_one_cell_are_exact():
    """The octahedron |x| + |y| + |z| < a inside the one cell of a box: its six tets each clipped by
    up to eight planes (the scratch of the kernels grows for them); volume 4 a^3 / 3 and eight faces
    of area sqrt(3) a^2 / 2 to round-off."""
    a = 0.5
    planes = [Plane((sx, sy, sz), (sx * a, 0, 0)) for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)]
    box = cf.structured_box([-1.0] * 3, [1.0] * 3, cells=1)
    cut = cf.cut_mesh(box, intersection(*planes))
    assert cut.dx(cf.NEG).size == pytest.approx(4 * a**3 / 3, rel=1e-13)
    assert [cut.part_area(k) for k in range(8)] == pytest.approx([np.sqrt(3) * a**2 / 2] * 8, rel=1e-13)
    check_identities(cut, 8.0)
