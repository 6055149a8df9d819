"""Level sets at the edges (issue 45): the zero rule on the level set's own local scale, mesh files
that cannot resolve what is asked, and the errors of user level sets and of the --surface flag,
through Python and the command line."""

import numpy as np
import pytest

from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.nodal_values import CutError, snapped_nodal_values
from cutfem.geometry.levelset import FunctionLevelSet
from cutfem.geometry.box import structured_box


def _norm_minus_one(x):
    return np.linalg.norm(x, axis=-1) - 1.0


def _exp_sphere(x):
    return (np.linalg.norm(x, axis=-1) - 1.0) * np.exp(10.0 * x[..., 0])


@pytest.mark.parametrize("f, bound", [(_norm_minus_one, 1e10), (_exp_sphere, 3.95e6)])
def test_a_generous_lipschitz_bound_does_not_move_the_surface(f, bound):
    """A true but generous bound once set the snap tolerance to 1e-12 L diam (0.043 for L = 1e10):
    nodes 0.04 from the unit sphere were zeroed and the area was 15.98 instead of 12.56.  The snap
    is local now: the band search gives the cut of the full evaluation, and only nodes on the
    sphere to round-off are zero."""
    box = structured_box([-1.25] * 3, [1.25] * 3, spacing=0.05)  # the box
    bounded = cut_mesh(box, FunctionLevelSet(f, lipschitz=bound))
    plain = cut_mesh(box, FunctionLevelSet(f))  # every node evaluated, no bound
    assert abs(plain.area - 4 * np.pi) < 0.05 * 4 * np.pi  # the discretization error of this level set
    assert abs(bounded.area - plain.area) < 1e-12 * plain.area
    assert bounded.n_tets == plain.n_tets and bounded.is_closed
    zero = bounded.points[bounded.values == 0]
    assert np.all(np.abs(np.linalg.norm(zero, axis=-1) - 1.0) < 1e-12)
    everywhere = snapped_nodal_values(box, FunctionLevelSet(f, lipschitz=bound))
    x = box.node_coordinates(np.flatnonzero(everywhere == 0))
    assert np.all(np.abs(np.linalg.norm(x, axis=-1) - 1.0) < 1e-12)


def test_generous_bound_snaps_the_nodes_on_a_plane_through_nodes():
    """Degenerate placements stay closed with a generous bound: a plane through a layer of nodes,
    its values zero to rounding (0.1 * k - 0.3 is not 0 in floating point), is snapped there."""
    box = structured_box([-1, -1, -1], [1, 1, 1], spacing=0.1)
    for lipschitz in (None, 1.0, 1e8):
        sphere_ish = FunctionLevelSet(lambda x: np.maximum(np.abs(x[..., 2] - 0.3), np.linalg.norm(x[..., :2], axis=-1) - 0.5) - 0.2,
                                      lipschitz=lipschitz)
        cut = cut_mesh(box, sphere_ish)
        assert cut.is_closed
        z = cut.points[cut.values == 0][:, 2]
        assert z.size and np.all(np.isclose(z, 0.1) | np.isclose(z, 0.5) | (np.abs(np.linalg.norm(cut.points[cut.values == 0][:, :2], axis=-1) - 0.7) < 1e-12))


# ------------------------------------------------------------------------------------------------
# the level set refused for what it is, with the cause and the fix (Python and command line)
# ------------------------------------------------------------------------------------------------

BOX = structured_box([-1.25] * 3, [1.25] * 3, spacing=0.25)


@pytest.mark.parametrize("bound", [np.inf, np.nan, 0.0, -1.0])
def test_a_lipschitz_bound_must_be_finite_and_positive(bound):
    """inf or NaN once gave "does not cut the background mesh" (NaN drops every cell of the band)."""
    from cutfem.geometry.shapes import Sphere

    sphere = Sphere(1.0)
    sphere.lipschitz = bound
    with pytest.raises(ValueError, match=r"a Lipschitz bound must be a finite positive number.*or None to evaluate every node"):
        cut_mesh(BOX, sphere)


@pytest.mark.parametrize("expression", ["-(x + y - 2.5)", "-(x + y + z - 3.75)", "-(x - 1.25)", "abs(x - 1.25)"])
@pytest.mark.parametrize("lipschitz", [None, 2.0])
def test_a_level_set_touching_the_box_on_its_boundary_is_not_told_to_refine(expression, lipschitz):
    """Zero only along an edge, a corner or a face of the box and positive inside: refining cannot
    help (the message said 'refine the mesh')."""
    with pytest.raises(CutError, match="touches the box only on its boundary") as info:
        cut_mesh(BOX, FunctionLevelSet.from_expression(expression, lipschitz=lipschitz))
    assert "refining the mesh cannot help" in str(info.value) and "Move the box or the level set" in str(info.value)


def _self_intersecting_sphere():
    """A sphere mesh whose north pole is pulled through the south: its fan crosses the far side."""
    from cutfem.geometry.surface import SurfaceMesh
    from cutfem.geometry.surface_meshes import sphere_mesh

    m = sphere_mesh(2)
    points = np.array(m.points)
    points[np.argmax(points[:, 2])] = [0.0, 0.0, -1.6]
    return SurfaceMesh(points, np.array(m.triangles))


def test_a_self_intersecting_surface_mesh_is_named_not_its_lipschitz_bound():
    from cutfem.geometry.signed_distance import SignedDistance

    box = structured_box([-1.3] * 3, [1.3] * 3, spacing=0.2)
    with pytest.raises(CutError) as info:
        cut_mesh(box, SignedDistance(_self_intersecting_sphere()))
    message = str(info.value)
    assert "surface mesh self-intersects" in message and "pairs of its triangles cross" in message and "near [" in message
    assert "declared" not in message and "Repair the mesh" in message


# ------------------------------------------------------------------------------------------------
# user functions and the --surface flag
# ------------------------------------------------------------------------------------------------


def test_a_huge_integer_in_an_expression_is_a_value_error():
    """The checker's own message formatted the 401-digit integer as a float: OverflowError (exit 1)."""
    with pytest.raises(ValueError, match="integer of about 401 digits .* too large for a float"):
        FunctionLevelSet.from_expression("1" + "0" * 400 + "*x + y")


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_an_exception_in_a_surface_files_phi_names_the_file_and_the_line(tmp_path):
    path = _write(tmp_path, "raising.py", "def phi(x):\n    d = {}\n    return d['inside phi']\n")
    levelset = FunctionLevelSet.from_file(path)
    with pytest.raises(ValueError, match=r"the surface file .*raising.py.*: phi\(x\) raised KeyError\('inside phi'\) at line 3") as info:
        levelset.value(np.zeros((2, 3)))
    assert isinstance(info.value.__cause__, KeyError)


@pytest.mark.parametrize("body, dtype", [("np.full(x.shape[:-1], 'a')", "dtype <U1"), ("np.full(x.shape[:-1], None)", "dtype object")])
def test_phi_returning_non_numbers_names_phi_and_the_dtype(tmp_path, body, dtype):
    """Strings gave numpy's 'could not convert string to float'; None became NaN ('NaN or infinite values')."""
    path = _write(tmp_path, "strings.py", f"import numpy as np\ndef phi(x):\n    return {body}\n")
    with pytest.raises(ValueError, match=rf"strings.py.*: phi\(x\) returned values of {dtype} .* it must return real numbers"):
        FunctionLevelSet.from_file(path).value(np.zeros((4, 3)))
    with pytest.raises(ValueError, match=rf"value\(x\) returned values of {dtype}"):  # a plain callable, through the cut
        cut_mesh(BOX, lambda x: np.full(x.shape[:-1], "a" if "U" in dtype else None))


def _cli(capsys, *args):
    from cutfem.runs.cli import main

    status = main(["run", "mean-curvature-cut", *args, "--quiet"])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def test_cli_surface_errors_exit_2_with_the_cause(tmp_path, capsys):
    raising = _write(tmp_path, "raising.py", "def phi(x):\n    return {}['inside phi']\n\nbox = (-1, -1, -1, 1, 1, 1)\n")
    status, _, err = _cli(capsys, "--surface", str(raising), "--spacing", "0.25")
    assert status == 2 and "phi(x) raised KeyError('inside phi') at line 2" in err
    status, _, err = _cli(capsys, "--surface", "1" + "0" * 400 + "*x + y", "--spacing", "0.25")
    assert status == 2 and "integer of about 401 digits" in err and "(407 characters)" in err
    status, _, err = _cli(capsys, "--surface", "", "--spacing", "0.25")
    assert status == 2 and "--surface is empty" in err and "directory" not in err


def test_cli_surface_expression_may_start_with_a_minus(capsys):
    """argparse read '-(...)' as an option: 'expected one argument'."""
    status, out, err = _cli(capsys, "--surface", "-(1-x**2-y**2-z**2)", "--box", "-1.3,-1.3,-1.3,1.3,1.3,1.3", "--spacing", "0.2")
    assert status == 0, err
    assert "expected one argument" not in err and "l2_error" in out


# ------------------------------------------------------------------------------------------------
# a surface from a mesh file: what it cannot give is said
# ------------------------------------------------------------------------------------------------


def _uv_sphere(n):
    import pyvista as pv

    from cutfem.geometry.surface import SurfaceMesh

    s = pv.Sphere(radius=1.0, theta_resolution=n, phi_resolution=n).triangulate()
    return SurfaceMesh(np.asarray(s.points, dtype=float), s.faces.reshape(-1, 4)[:, 1:])


def test_mesh_file_notes_below_the_facet_size():
    """A 48 x 48 sphere mesh (median edge 0.074): the L2 error against the sphere grows from 0.018 at
    spacing 0.0375 to 0.070 at 0.0125; below half the median edge the run says so."""
    from cutfem.geometry.signed_distance import SignedDistance
    from cutfem.problems.common import mesh_file_notes

    distance = SignedDistance(_uv_sphere(48))
    coarse, fine = mesh_file_notes(distance, 0.05), mesh_file_notes(distance, 0.025)
    assert len(coarse) == 1 and "no l2_error column" in coarse[0]
    assert len(fine) == 2 and "below 0.5 times the facet size of the surface mesh (median edge 0.0736)" in fine[1]
    assert "Use spacing >= 0.037" in fine[1]
    assert mesh_file_notes(FunctionLevelSet(_norm_minus_one), 0.001) == []


def test_cli_mesh_file_run_says_why_there_is_no_error_column(tmp_path, capsys):
    import json

    from cutfem.geometry.surface import write_surface

    path = tmp_path / "sphere12.stl"
    write_surface(_uv_sphere(12), path)
    out_json = tmp_path / "run.json"
    status, out, err = _cli(capsys, "--surface", str(path), "--spacing", "0.1", "--json", str(out_json))
    assert status == 0, err
    assert "note (spacing=0.1): no l2_error column" in out
    assert "note (spacing=0.1): spacing 0.1 is below 0.5 times the facet size" in out
    record = json.loads(out_json.read_text())["records"][0]
    assert any("facet size" in note for note in record["notes"])


def test_a_surface_files_bad_lipschitz_names_the_file(tmp_path):
    path = _write(tmp_path, "bound.py", "def phi(x):\n    return x[..., 0]\n\nlipschitz = float('inf')\n")
    with pytest.raises(ValueError, match=r"the surface file .*bound.py': lipschitz must be a finite positive number, got inf"):
        FunctionLevelSet.from_file(path)
