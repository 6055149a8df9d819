"""Tests for cutfem.geometry.surface_meshes: the generated tori (docs/math.md §6.1) and icosahedral spheres.

Expected numbers come from closed-form geometry (torus trapezoid areas, icosahedron formulas),
never from the code under test.
"""

import numpy as np
import pytest

from cutfem.geometry.surface_meshes import TORUS_FAMILIES, sphere_mesh, torus_mesh


def torus_rho(x, R, r):
    """Exact signed distance to the torus (docs/math.md §1)."""
    return np.sqrt(x[:, 2] ** 2 + (np.hypot(x[:, 0], x[:, 1]) - R) ** 2) - r


def structured_torus_area(n, R, r):
    """Exact area of the structured n x n/2 torus mesh, summed over its planar trapezoid cells.

    Cell (i, j): parallel sides 2 rho_j sin(pi/n) and 2 rho_{j+1} sin(pi/n) (rho = R + r cos p),
    perpendicular to the cell's mirror plane t = t_i + pi/n; the height is the distance between
    their midpoints (rho cos(pi/n), r sin p) in that plane.
    """
    m = n // 2
    p = 2 * np.pi * np.arange(m + 1) / m
    rho = R + r * np.cos(p)
    s, c = np.sin(np.pi / n), np.cos(np.pi / n)
    sides = 2 * rho * s
    height = np.hypot(np.diff(rho) * c, r * np.diff(np.sin(p)))
    return n * np.sum(0.5 * (sides[:-1] + sides[1:]) * height)


def rate(h, e):
    """Least-squares slope of log e against log h."""
    return np.polyfit(np.log(h), np.log(e), 1)[0]


# ----------------------------------------------------------------------------------------------
# torus
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("family", TORUS_FAMILIES)
@pytest.mark.parametrize("n", [6, 12])
def test_torus_topology(family, n):
    mesh = torus_mesh(n, family)
    nodes = n * (n // 2)
    assert mesh.n_points == nodes
    assert mesh.n_triangles == 2 * nodes
    assert mesh.n_edges == 3 * nodes
    assert mesh.euler_characteristic == 0
    assert mesh.h == pytest.approx(nodes**-0.5, rel=1e-15)
    assert mesh.flipped_components == 0  # generated outward


@pytest.mark.parametrize("family", TORUS_FAMILIES)
@pytest.mark.parametrize("R, r", [(1.0, 0.5), (2.0, 0.7)])
def test_torus_nodes_on_torus(family, R, r):
    mesh = torus_mesh(16, family, R=R, r=r, seed=3)
    assert np.max(np.abs(torus_rho(mesh.points, R, r))) < 1e-14


@pytest.mark.parametrize("n, R, r", [(8, 1.0, 0.5), (20, 2.0, 0.3)])
def test_structured_and_flipped_area_exact(n, R, r):
    expected = structured_torus_area(n, R, r)
    assert torus_mesh(n, "structured", R=R, r=r).area == pytest.approx(expected, rel=1e-13)
    # cells are planar trapezoids: the diagonal does not change the area
    assert torus_mesh(n, "flipped", R=R, r=r, seed=5).area == pytest.approx(expected, rel=1e-13)


@pytest.mark.parametrize("family", TORUS_FAMILIES)
def test_torus_area_converges_at_rate_two(family):
    R, r = 1.0, 0.5
    exact = 4 * np.pi**2 * R * r
    meshes = [torus_mesh(n, family, R=R, r=r, seed=1) for n in (16, 32, 64, 128)]
    h = [m.h for m in meshes]
    err = [abs(m.area - exact) for m in meshes]
    assert rate(h, err) == pytest.approx(2.0, abs=0.1)
    assert err[-1] / exact < 1e-3


def test_torus_normals_outward():
    R, r = 1.0, 0.5
    mesh = torus_mesh(32, "perturbed-flipped", seed=2)
    x = mesh.centroids
    axis_point = R * x * np.array([1, 1, 0]) / np.hypot(x[:, 0], x[:, 1])[:, None]
    exact = (x - axis_point) / np.linalg.norm(x - axis_point, axis=1)[:, None]
    assert np.allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-14)
    assert np.min(np.einsum("ij,ij->i", mesh.normals, exact)) > 0.9
    assert mesh.enclosed_volume == pytest.approx(2 * np.pi**2 * R * r**2, rel=0.05)


def test_flipped_differs_from_structured_with_same_points():
    structured = torus_mesh(12, "structured")
    flipped = torus_mesh(12, "flipped", seed=0)
    assert np.array_equal(structured.points, flipped.points)
    assert not np.array_equal(structured.triangles, flipped.triangles)
    assert not np.array_equal(structured.edges, flipped.edges)


def test_torus_seeding():
    for family in ("flipped", "perturbed", "perturbed-flipped"):
        a, b, c = (torus_mesh(10, family, seed=s) for s in (7, 7, 8))
        assert np.array_equal(a.points, b.points) and np.array_equal(a.triangles, b.triangles)
        assert not (np.array_equal(a.points, c.points) and np.array_equal(a.triangles, c.triangles))
    # the structured family ignores the seed
    assert np.array_equal(torus_mesh(10, seed=1).triangles, torus_mesh(10, seed=2).triangles)
    # documented: one stream, perturbed-flipped = nodes of perturbed + diagonals of flipped
    both = torus_mesh(10, "perturbed-flipped", seed=4)
    assert np.array_equal(both.points, torus_mesh(10, "perturbed", seed=4).points)
    assert np.array_equal(both.triangles, torus_mesh(10, "flipped", seed=4).triangles)


def test_torus_perturbation_bounded():
    n, m = 12, 6
    mesh = torus_mesh(n, "perturbed", seed=9)
    x = mesh.points
    t = np.arctan2(x[:, 1], x[:, 0])
    p = np.arctan2(x[:, 2], np.hypot(x[:, 0], x[:, 1]) - 1.0)
    i, j = np.divmod(np.arange(n * m), m)
    dt = np.angle(np.exp(1j * (t - 2 * np.pi * i / n))) / (2 * np.pi / n)
    dp = np.angle(np.exp(1j * (p - 2 * np.pi * j / m))) / (2 * np.pi / m)
    assert np.max(np.abs(dt)) <= 0.25 + 1e-12 and np.max(np.abs(dp)) <= 0.25 + 1e-12
    assert np.max(np.abs(dt)) > 0.1 and np.max(np.abs(dp)) > 0.1  # really perturbed


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(n=7), "even"),
        (dict(n=4), ">= 6"),
        (dict(n=8.0), "integer"),
        (dict(n=8, family="random"), "structured, flipped, perturbed, perturbed-flipped"),
        (dict(n=8, R=0.5, r=0.5), "r < R"),
        (dict(n=8, r=-0.1), "positive"),
    ],
)
def test_torus_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        torus_mesh(**kwargs)


# ----------------------------------------------------------------------------------------------
# sphere
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("level", [0, 1, 3])
def test_sphere_counts_and_nodes(level):
    radius, center = 2.5, np.array([0.3, -1.0, 2.0])
    mesh = sphere_mesh(level, radius, center)
    assert mesh.n_points == 10 * 4**level + 2
    assert mesh.n_edges == 30 * 4**level
    assert mesh.n_triangles == 20 * 4**level
    assert mesh.euler_characteristic == 2
    assert np.max(np.abs(np.linalg.norm(mesh.points - center, axis=1) - radius)) < 1e-14 * radius * 4
    outward = np.einsum("ij,ij->i", mesh.normals, mesh.centroids - center)
    assert np.all(outward > 0)


def test_icosahedron_exact_area_and_volume():
    radius = 1.7
    a = 4 * radius / np.sqrt(10 + 2 * np.sqrt(5))  # edge of the inscribed regular icosahedron
    mesh = sphere_mesh(0, radius)
    assert np.allclose(mesh.edge_lengths, a, rtol=1e-14)
    assert mesh.area == pytest.approx(5 * np.sqrt(3) * a**2, rel=1e-14)
    assert mesh.enclosed_volume == pytest.approx(5 / 12 * (3 + np.sqrt(5)) * a**3, rel=1e-14)


def test_sphere_area_and_volume_converge():
    radius = 1.3
    meshes = [sphere_mesh(level, radius, (1.0, 2.0, 3.0)) for level in (1, 2, 3, 4)]
    h = [m.h for m in meshes]
    area_err = [abs(m.area - 4 * np.pi * radius**2) for m in meshes]
    vol_err = [abs(m.enclosed_volume - 4 / 3 * np.pi * radius**3) for m in meshes]
    assert rate(h, area_err) == pytest.approx(2.0, abs=0.15)
    assert rate(h, vol_err) == pytest.approx(2.0, abs=0.15)
    assert area_err[-1] / (4 * np.pi * radius**2) < 2e-3


@pytest.mark.parametrize(
    "kwargs, match", [(dict(level=-1), ">= 0"), (dict(radius=0.0), "positive"), (dict(center=(0, 0)), "center")]
)
def test_sphere_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        sphere_mesh(**kwargs)
