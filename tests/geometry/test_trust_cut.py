"""No silent open surfaces: overlapping surface components, a too small Lipschitz bound and an
open S_h raise errors that name the cause and the fix, through Python and the command line."""

import dataclasses
import subprocess
import sys
from pathlib import Path

import meshio
import numpy as np
import pytest

from cutfem.runs.cli import main
from cutfem.geometry.cut import _check_closed, cut_mesh
from cutfem.geometry.nodal_values import CutError
from cutfem.geometry.levelset import FunctionLevelSet
from cutfem.geometry.shapes import Sphere, Torus
from cutfem.geometry.signed_distance import SignedDistance
from cutfem.geometry.box import structured_box
from cutfem.geometry.surface import SurfaceMesh, read_surface
from cutfem.geometry.surface_meshes import sphere_mesh

ROOT = Path(__file__).resolve().parents[2]


def union(*meshes):
    """Points and triangles of several meshes side by side (no validation)."""
    points, triangles, n = [], [], 0
    for m in meshes:
        points.append(np.asarray(m[0]))
        triangles.append(np.asarray(m[1]) + n)
        n += len(m[0])
    return np.vstack(points), np.vstack(triangles)


def sphere(center, radius=1.0, level=2):
    m = sphere_mesh(level, radius=radius, center=center)
    return m.points, m.triangles


def beam(half):
    """A box [-half, half] as 8 corners and 12 outward triangles."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * half
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tri = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return corners, tri


def write_ply(path, points, triangles):
    meshio.write(path, meshio.Mesh(points, [("triangle", np.asarray(triangles, dtype=np.int32))]))
    return path


OVERLAP = union(sphere((0.0, 0.0, 0.0)), sphere((0.8, 0.0, 0.0)))


def test_beam_is_a_valid_closed_mesh():
    mesh = SurfaceMesh(*beam(np.array([1.0, 0.5, 0.25])))
    assert mesh.euler_characteristic == 2 and mesh.flipped_components == 0
    assert mesh.enclosed_volume == pytest.approx(8 * 0.125)


def test_overlapping_spheres_are_refused_by_read_surface(tmp_path):
    path = write_ply(tmp_path / "two.ply", *OVERLAP)
    with pytest.raises(ValueError, match=r"closed components of the surface intersect: 1 pair\(s\).*\(0, 1\).*merge them"):
        read_surface(path)
    with pytest.raises(ValueError, match="intersect"):
        SurfaceMesh(*OVERLAP)


def test_crossing_beams_without_a_vertex_inside_the_other_are_refused():
    """A plus sign of two beams: no vertex of either lies inside the other, only edges cross."""
    a = beam(np.array([2.0, 0.2, 0.2]))
    b = beam(np.array([0.2, 2.0, 0.1]))
    with pytest.raises(ValueError, match="intersect"):
        SurfaceMesh(*union(a, b))


def test_nested_shells_are_refused_and_disjoint_components_accepted():
    with pytest.raises(ValueError, match=r"nested: 1 component\(s\).*\(1, 0\)"):
        SurfaceMesh(*union(sphere((0.0, 0.0, 0.0)), sphere((0.1, 0.0, 0.0), radius=0.5)))
    # bounding boxes overlap, surfaces 0.12 apart: legal, two spheres
    mesh = SurfaceMesh(*union(sphere((0.0, 0.0, 0.0)), sphere((1.5, 1.5, 0.0))))
    assert mesh.euler_characteristic == 4


def test_overlapping_spheres_signed_distance_is_refused_before_the_cut():
    """SignedDistance validates through SurfaceMesh: overlapping parts are refused when it is built."""
    points, triangles = OVERLAP
    with pytest.raises(ValueError, match=r"closed components of the surface intersect: 1 pair\(s\)"):
        SignedDistance(type("Soup", (), {"points": points, "triangles": triangles})())


def test_overlapping_spheres_through_the_command_line(tmp_path):
    path = write_ply(tmp_path / "two.ply", *OVERLAP)
    proc = subprocess.run(
        [sys.executable, "-m", "cutfem.runs.cli", "run", "mean-curvature-cut", "--surface", str(path), "--spacing", "0.25"],
        capture_output=True, text=True, cwd=ROOT,
    )
    assert proc.returncode == 2
    assert "closed components of the surface intersect" in proc.stderr
    assert proc.stdout.count("\n") <= 1  # no table


def _ant():
    try:
        import pyvista.examples
    except ImportError:  # pragma: no cover
        return None
    path = Path(pyvista.examples.__file__).parent / "ant.ply"
    return path if path.exists() else None


@pytest.mark.skipif(_ant() is None, reason="pyvista's bundled ant.ply is not installed")
def test_pyvista_ant_is_refused(capsys):
    with pytest.raises(ValueError, match=r"intersect: 7 pair\(s\)"):
        read_surface(_ant())
    assert main(["run", "mean-curvature-cut", "--surface", str(_ant()), "--spacing", "0.25", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "closed components of the surface intersect" in err


def three_sphere(lipschitz):
    """phi = 3 (|x| - 1): the unit sphere, true Lipschitz bound 3."""
    return FunctionLevelSet(lambda x: 3.0 * (np.linalg.norm(x, axis=-1) - 1.0), lipschitz=lipschitz)


BOX = structured_box([-1.5] * 3, [1.5] * 3, spacing=0.1)


@pytest.mark.parametrize("lipschitz", [0.2, 1.0, 2.9])
def test_too_small_lipschitz_bound_raises(lipschitz):
    with pytest.raises(CutError, match="Lipschitz"):
        cut_mesh(BOX, three_sphere(lipschitz))


def test_lipschitz_violation_names_the_bound_seen():
    with pytest.raises(CutError, match=r"bound L = 1: .* reaches 3(\.0+)? .*levelset.lipschitz >= 3"):
        cut_mesh(BOX, three_sphere(1.0))


def test_true_lipschitz_bound_cuts_the_same_surface_as_no_bound():
    banded = cut_mesh(BOX, three_sphere(3.0))
    full = cut_mesh(BOX, three_sphere(None))
    assert banded.is_closed and banded.euler_characteristic == 2
    assert banded.n_triangles == full.n_triangles
    assert banded.area == pytest.approx(full.area, rel=1e-12)
    assert banded.area == pytest.approx(4 * np.pi, rel=0.02)


@pytest.mark.parametrize("levelset, chi, area", [(Torus(1.0, 0.5), 0, 2 * np.pi**2), (Sphere(1.0), 2, 4 * np.pi)])
def test_valid_surfaces_still_cut_closed(levelset, chi, area):
    box = structured_box([-1.6, -1.6, -1.6], [1.6, 1.6, 1.6], spacing=0.1)
    cut = cut_mesh(box, levelset)
    assert cut.is_closed and cut.euler_characteristic == chi
    assert cut.area == pytest.approx(area, rel=0.02)


def test_open_cut_surface_raises_with_the_cause():
    cut = cut_mesh(BOX, Sphere(1.0))
    holed = dataclasses.replace(cut, triangles=cut.triangles[1:], triangle_tets=cut.triangle_tets[1:])
    with pytest.raises(CutError, match=r"not a closed manifold: 3 edges lie in one triangle only.*Lipschitz bound"):
        _check_closed(holed, check_boundary=True, band=True)
    with pytest.raises(CutError, match="touches or crosses itself"):
        _check_closed(holed, check_boundary=False, band=False)
    doubled = dataclasses.replace(cut, triangles=np.vstack([cut.triangles, cut.triangles[:1]]))
    with pytest.raises(CutError, match="3 in more than two"):
        _check_closed(doubled, check_boundary=True, band=False)


def test_surface_leaving_the_box_is_open_only_on_the_box_faces():
    plane = FunctionLevelSet(lambda x: x[..., 2] - 0.2 * x[..., 0] - 0.05)
    box = structured_box([-1.0] * 3, [1.0] * 3, cells=6)
    cut = cut_mesh(box, plane, check_boundary=False)  # accepted: its open edges lie on the box faces
    assert not cut.is_closed and cut.euler_characteristic == 1
    holed = dataclasses.replace(cut, triangles=cut.triangles[1:], triangle_tets=cut.triangle_tets[1:])
    with pytest.raises(CutError, match="one triangle only"):  # a hole inside the box is still refused
        _check_closed(holed, check_boundary=False, band=True)


def test_zero_rule_is_local_without_a_lipschitz_bound():
    """A level set whose values span many orders of magnitude: the snap scale is each node's
    neighbourhood, not the box's largest value (which zeroed values of 1e-10 and gave area 4.57)."""
    from cutfem.geometry.cut import NEG
    from cutfem.geometry.nodal_values import snapped_nodal_values

    box = structured_box([-1, -1, -1], [1, 1, 1], spacing=0.1)
    scaled = FunctionLevelSet.from_expression("z * exp(20 * x)")
    cut = cut_mesh(box, scaled, check_boundary=False)
    assert abs(cut.area - 4.0) < 1e-12
    assert abs(cut.dx(NEG).integrate(lambda x: np.ones(x.shape[:-1])) - 4.0) < 1e-9
    values = snapped_nodal_values(box, scaled)
    z = box.node_coordinates(np.arange(box.n_points))[:, 2]
    np.testing.assert_array_equal(values == 0, np.abs(z) < 1e-12)  # exactly the nodes on the plane
    tiny = FunctionLevelSet(lambda x: x[..., 2] + 1e-16 * (np.abs(x[..., 2]) < 1e-12))  # rounding noise on the plane
    assert np.count_nonzero(snapped_nodal_values(box, tiny) == 0) == np.count_nonzero(np.abs(z) < 1e-12)


@pytest.mark.parametrize("scale", ["1e-320", "1e-300", "1e300", "1e308"])
def test_level_sets_of_extreme_scale_keep_unit_normals(scale):
    """|grad phi_h|^2 underflows or overflows for values near 1e-300 or 1e300; the normals are
    rescaled, so the surface and its measure are those of the unscaled plane."""
    box = structured_box([-1, -1, -1], [1, 1, 1], spacing=0.25)
    cut = cut_mesh(box, FunctionLevelSet.from_expression(f"z * {scale}"), check_boundary=False)
    np.testing.assert_allclose(cut.normals, np.tile([0.0, 0.0, 1.0], (cut.n_tets, 1)), atol=1e-15)
    assert abs(cut.ds().integrate(lambda x: np.ones(x.shape[:-1])) - 4.0) < 1e-12
