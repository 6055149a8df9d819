"""User level sets (not distances) through the library, the registry and the command line.

The tanglecube sum_i (x_i^4 - 5 x_i^2) + 11.8 = 0 (genus 5) and a sphere or ellipsoid written as a
polynomial: Newton closest points, the exact mean curvature vector of docs/math.md §1 at them,
derivatives by differences, and the clear errors for callables of the wrong shape.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import cutfem
from cutfem.runs.cli import main
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.levelset import FunctionLevelSet
from cutfem.geometry.shapes import Ellipsoid, Sphere
from cutfem.geometry.box import structured_box

ROOT = Path(__file__).resolve().parents[2]
TANGLE = "x**4 - 5*x**2 + y**4 - 5*y**2 + z**4 - 5*z**2 + 11.8"
TANGLE_BOX = "-2.4,-2.4,-2.4,2.4,2.4,2.4"


def tangle(x):
    return np.sum(x**4 - 5.0 * x**2, axis=-1) + 11.8


def tangle_grad(x):
    return 4.0 * x**3 - 10.0 * x


def tangle_hess(x):
    return np.eye(3) * (12.0 * x**2 - 10.0)[..., None, :]


def near_tangle(n, seed=0, band=0.15):
    """n points within about ``band`` of the tanglecube (first-order projections pushed off along n)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-2.3, 2.3, (40 * n, 3))
    for _ in range(3):
        g = tangle_grad(x)
        x = x - (tangle(x) / np.sum(g * g, axis=-1))[:, None] * g
    x = x[np.abs(tangle(x)) < 1e-3][:n]
    assert len(x) == n
    g = tangle_grad(x)
    return x + rng.uniform(-band, band, (n, 1)) * g / np.linalg.norm(g, axis=1, keepdims=True)


# ----------------------------------------------------------------------------------------------
# closest point and exact fields
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("derivatives", ["analytic", "values only"])
def test_tanglecube_closest_point_is_on_the_surface_along_the_normal(derivatives):
    ls = FunctionLevelSet(tangle, tangle_grad, tangle_hess) if derivatives == "analytic" else FunctionLevelSet(tangle)
    x = near_tangle(3000)
    p = ls.closest_point(x)
    g = tangle_grad(p)
    scale = np.linalg.norm(g, axis=1) * np.maximum(1.0, np.abs(x).max(axis=1))
    assert np.all(np.abs(tangle(p)) <= 1e-12 * scale)  # the documented guarantee
    assert np.abs(tangle(p)).max() < 1e-12  # and absolutely (measured 2e-14)
    n = g / np.linalg.norm(g, axis=1, keepdims=True)
    d = x - p
    off_normal = np.linalg.norm(np.cross(d, n), axis=1)
    if derivatives == "analytic":
        assert off_normal.max() < 1e-13  # measured 3e-16
    else:  # the difference gradient is exact to about 1e-10
        assert np.all(off_normal <= 1e-9 * np.linalg.norm(d, axis=1) + 1e-12)
    assert np.all(np.linalg.norm(d, axis=1) < 0.16)


def test_polynomial_sphere_matches_the_sphere_class():
    R, c = 0.8, np.array([0.1, -0.2, 0.05])
    poly = FunctionLevelSet(lambda x: np.sum((x - c) ** 2, axis=-1) - R**2, lambda x: 2.0 * (x - c),
                            lambda x: np.broadcast_to(2.0 * np.eye(3), x.shape + (3,)))
    sphere = Sphere(R, center=c)
    rng = np.random.default_rng(1)
    u = rng.normal(size=(500, 3))
    x = c + u / np.linalg.norm(u, axis=1, keepdims=True) * rng.uniform(0.5 * R, 1.6 * R, (500, 1))
    np.testing.assert_allclose(poly.closest_point(x), sphere.closest_point(x), atol=1e-14)
    np.testing.assert_allclose(poly.exact_mean_curvature_vector(x), sphere.exact_mean_curvature_vector(x), atol=1e-13)
    np.testing.assert_allclose(poly.exact_normal(x), sphere.exact_normal(x), atol=1e-14)
    np.testing.assert_allclose(poly.exact_mean_curvature(x), 2.0 / R, rtol=1e-13)
    # the same sphere as a text expression: derivatives by differences
    expr = FunctionLevelSet.from_expression(f"(x - {c[0]})**2 + (y - {c[1]})**2 + (z - {c[2]})**2 - {R**2}")
    np.testing.assert_allclose(expr.closest_point(x), sphere.closest_point(x), atol=1e-10)
    np.testing.assert_allclose(expr.exact_mean_curvature_vector(x), sphere.exact_mean_curvature_vector(x), atol=1e-6)


def test_polynomial_ellipsoid_closest_point_matches_the_ellipsoid_class():
    """Newton on the closest-point system against the Ellipsoid's own multiplier iteration."""
    ell = Ellipsoid(1.0, 0.8, 0.6)
    poly = FunctionLevelSet(ell.value, ell.gradient, ell.hessian)
    rng = np.random.default_rng(2)
    x = rng.uniform(-1.2, 1.2, (4000, 3))
    x = x[np.abs(ell.value(x)) < 0.3]
    assert len(x) > 500
    np.testing.assert_allclose(poly.closest_point(x), ell.closest_point(x), atol=1e-13)
    np.testing.assert_allclose(poly.exact_mean_curvature_vector(x), ell.exact_mean_curvature_vector(x), atol=1e-12)


def test_finite_differences_agree_with_analytic_derivatives():
    x = near_tangle(500, seed=3)
    values_only, with_grad = FunctionLevelSet(tangle), FunctionLevelSet(tangle, tangle_grad)
    full = FunctionLevelSet(tangle, tangle_grad, tangle_hess)
    g, h = tangle_grad(x), tangle_hess(x)
    assert np.abs(values_only.gradient(x) - g).max() < 1e-9 * np.abs(g).max()  # measured 9e-11
    assert np.abs(values_only.hessian(x) - h).max() < 1e-7 * np.abs(h).max()  # measured 1.2e-8
    assert np.abs(with_grad.hessian(x) - h).max() < 1e-9 * np.abs(h).max()  # measured 3e-11
    H = full.exact_mean_curvature_vector(x)
    assert np.abs(values_only.exact_mean_curvature_vector(x) - H).max() < 1e-6 * np.abs(H).max()  # measured 6e-8


def test_projection_refuses_points_it_cannot_project():
    ls = FunctionLevelSet.from_expression(TANGLE)
    with pytest.raises(ValueError, match="undefined at 1 point.*grad phi = 0"):
        ls.closest_point(np.zeros((1, 3)))  # the centre: grad phi = 0
    with pytest.raises(ValueError, match=r"did not converge in 12 Newton steps for 1 of 2 point.*near the surface"):
        ls.closest_point(np.array([[0.3, 0.2, 0.1], [1.2, 1.1, 0.2]]))  # the first is deep inside the tubes


# ----------------------------------------------------------------------------------------------
# through the registry
# ----------------------------------------------------------------------------------------------
def test_tanglecube_through_the_registry_converges():
    ls = FunctionLevelSet(tangle, tangle_grad, tangle_hess, bounds=([-2.3] * 3, [2.3] * 3))
    res = cutfem.run("mean-curvature-cut", levels=[0.3, 0.2], surface=ls)
    e = [r["l2_error"] for r in res.records]
    assert e[1] < 0.9 * e[0]  # measured 6.39 -> 5.35 (rate 0.44 on these coarse meshes)
    for r in res.records:
        assert 90 < r["area"] < 105  # area of the tanglecube about 100.9 (finer meshes)
        assert np.linalg.norm(r["integral_H"]) < 1e-8 * r["area"]


def test_polynomial_ellipsoid_through_the_registry_equals_the_named_ellipsoid():
    """Same nodal values and box: same H_h, and the exact fields agree, so the errors agree."""
    ell = Ellipsoid(1.0, 0.8, 0.6)
    expr = FunctionLevelSet.from_expression("x**2 + (y/0.8)**2 + (z/0.6)**2 - 1", bounds=ell.bounds())
    a = cutfem.run("mean-curvature-cut", levels=[0.2], surface="ellipsoid").records[0]
    b = cutfem.run("mean-curvature-cut", levels=[0.2], surface=expr).records[0]
    assert a["dofs"] == b["dofs"]
    assert b["l2_error"] == pytest.approx(a["l2_error"], rel=1e-7)


# ----------------------------------------------------------------------------------------------
# through the command line
# ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tangle_reference():
    """The tanglecube at spacing 0.3 in the box [-2.4, 2.4]^3 with analytic derivatives."""
    ls = FunctionLevelSet(tangle, tangle_grad, tangle_hess)
    return cutfem.run("mean-curvature-cut", levels=[0.3], surface=ls, box=TANGLE_BOX).records[0]


def test_expression_surface_through_the_command_line(tangle_reference):
    out = subprocess.run(
        [sys.executable, "-m", "cutfem.runs.cli", "run", "mean-curvature-cut", "--surface", TANGLE, "--box", TANGLE_BOX,
         "--levels", "0.3", "--json", "-"],
        capture_output=True, text=True, cwd=ROOT, check=True,
    ).stdout
    rec = json.loads(out)["records"][0]
    # same box and nodal values as the run with analytic derivatives: the errors differ by the
    # difference derivatives in the exact field only
    assert rec["dofs"] == tangle_reference["dofs"]
    assert rec["l2_error"] == pytest.approx(tangle_reference["l2_error"], rel=1e-6)


def test_python_file_surface_through_the_command_line(tmp_path, capsys, tangle_reference):
    path = tmp_path / "tangle.py"
    path.write_text(
        "import numpy as np\n"
        "def phi(x):\n    return np.sum(x**4 - 5*x**2, axis=-1) + 11.8\n"
        "def grad(x):\n    return 4*x**3 - 10*x\n"
        "def hessian(x):\n    return np.eye(3) * (12*x**2 - 10)[..., None, :]\n"
        "box = (-2.3, -2.3, -2.3, 2.3, 2.3, 2.3)\n"
    )
    assert main(["run", "mean-curvature-cut", "--surface", str(path), "--levels", "0.3", "--json", "-"]) == 0
    rec = json.loads(capsys.readouterr().out)["records"][0]
    # the file's box grown by 0.1 and rounded to the spacing is the reference box [-2.4, 2.4]^3
    assert rec["dofs"] == tangle_reference["dofs"]
    assert rec["l2_error"] == pytest.approx(tangle_reference["l2_error"], rel=1e-9)


@pytest.mark.parametrize("argv,pattern", [
    (["--surface", TANGLE, "--levels", "0.3"], r"no known bounding box: give the background box, --box"),
    (["--surface", "x^2 + y^2 + z^2 - 1", "--box", "-2,-2,-2,2,2,2"], r"\^, which is not a power in Python: write \*\*"),
    (["--surface", "x**2 + os.system(1)", "--box", "-2,-2,-2,2,2,2"], r"calls 'os.system\(1\)', which is not allowed"),
    (["--surface", "x**2 + w**2 - 1", "--box", "-2,-2,-2,2,2,2"], r"unknown name 'w'"),
    (["--surface", "missing.stl"], r"--surface: there is no file 'missing.stl' \(looked in"),
    (["--surface", "missing.py"], r"'missing.py' does not exist"),
])
def test_bad_user_surfaces_are_one_line_and_exit_2(argv, pattern, capsys):
    assert main(["run", "mean-curvature-cut", *argv, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    import re

    assert re.search(pattern, err), err


def test_python_file_without_phi_is_refused(tmp_path, capsys):
    path = tmp_path / "empty.py"
    path.write_text("import numpy as np\nbox = (-1, -1, -1, 1, 1, 1)\n")
    assert main(["run", "mean-curvature-cut", "--surface", str(path), "--quiet"]) == 2
    assert "defines no function phi(x)" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# callables of the wrong shape
# ----------------------------------------------------------------------------------------------
WRONG = [
    (lambda x: np.sum(x**2, axis=-1, keepdims=True) - 1, r"returned shape \(\d+, 1\).*must return shape \(\d+,\).*keepdims"),
    (lambda x: float(np.sum(x**2)) - 1, r"returned shape \(\).*must return shape \(\d+,\).*one number for all the points"),
    (lambda x: x[0] ** 2 + x[1] ** 2 + x[2] ** 2 - 1, r"returned shape \(3,\).*must return shape \(\d+,\).*write x\[\.\.\., 0\]"),
]


@pytest.mark.parametrize("fn,pattern", WRONG)
def test_wrong_shape_callables_get_the_documented_error(fn, pattern):
    with pytest.raises(ValueError, match=pattern):
        cutfem.run("mean-curvature-cut", levels=[0.5], surface=fn, box="-2,-2,-2,2,2,2")
    with pytest.raises(ValueError, match=pattern):  # also when cutting with the plain callable
        cut_mesh(structured_box([-2.0] * 3, [2.0] * 3, cells=[8] * 3), fn)


def test_wrong_shape_derivatives_get_the_documented_error():
    x = np.random.default_rng(4).uniform(-1, 1, (7, 3))
    ls = FunctionLevelSet(tangle, gradient=lambda x: np.array([x[..., 0], x[..., 1], x[..., 2]]))
    with pytest.raises(ValueError, match=r"gradient\(x\) returned shape \(3, 7\).*must return shape \(7, 3\).*np.stack"):
        ls.gradient(x)
    ls = FunctionLevelSet(lambda x: x[:, 0] ** 2 + x[:, 1] ** 2 + x[:, 2] ** 2 - 1)  # fine for (n, 3) only
    assert ls.value(x).shape == (7,)
    with pytest.raises(ValueError, match=r"value\(x\) returned shape \(7, 3\) for points x of shape \(7, 6, 3\)"):
        ls.gradient(x)  # the differences call it on (n, 6, 3)


def test_complex_level_set_values_are_refused():
    phi = FunctionLevelSet(lambda x: np.sum(x**2, axis=-1) - 1 + 0j)
    with pytest.raises(ValueError, match="complex values"):
        phi.value(np.zeros((2, 3)))


def test_surface_file_that_exits_or_declares_nonsense_is_reported(tmp_path):
    exits = tmp_path / "exits.py"
    exits.write_text("import sys\nsys.exit(3)\n")
    with pytest.raises(ValueError, match="SystemExit"):
        FunctionLevelSet.from_file(exits)
    words = tmp_path / "words.py"
    words.write_text("import numpy as np\ndef phi(x):\n    return np.sum(x**2, axis=-1) - 1\nlipschitz = 'one'\n")
    with pytest.raises(ValueError, match="lipschitz must be a finite positive number, got 'one'"):
        FunctionLevelSet.from_file(words)
