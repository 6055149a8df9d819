"""The hosted problems: rates, invariants and the qualitative behaviour reported in the paper (docs/math.md §3-4)."""

import numpy as np
import pytest

import cutfem
from cutfem.fem.norms import fitted_rate
from cutfem.runs.registry import ProblemError


def _fit(result, key):
    return fitted_rate([r["h"] for r in result.records], [r[key] for r in result.records])


def _assert_zero_integral(result):
    """An identity of the exact discrete solution: iterative solves (n > DIRECT_LIMIT) change it by
    1^T r, the sum of the residual, so the meshed runs that check it ask for the direct solver."""
    for r in result.records:
        # sum_j (M H)_j = sum_j (A X)_j - sum_j (J H)_j = 0: A and J annihilate constants
        assert np.max(np.abs(r["integral_H"])) < 1e-9 * r["area"]


def test_sphere_meshed_tends_to_2_over_R_n():
    res = cutfem.run("mean-curvature-meshed", levels=[8, 16, 32, 64], surface="sphere", radius=2.0)
    assert _fit(res, "l2_error") >= 1.0
    # H_h . n -> 2/R pointwise at the nodes
    poly = res.records[-1]["fields"]["surface"]
    assert np.max(np.abs(poly.point_data["mean_curvature"] - 1.0)) < 0.05
    _assert_zero_integral(res)


def test_sphere_cut_rate_at_least_one():
    res = cutfem.run("mean-curvature-cut", levels=[0.4, 0.2, 0.1], surface="sphere")
    assert _fit(res, "l2_error") >= 1.0
    _assert_zero_integral(res)


@pytest.mark.parametrize("family", ["structured", "flipped", "perturbed"])
def test_torus_meshed_stabilized_rate_at_least_one(family):
    seed = {} if family == "structured" else {"seed": 3}  # the structured grid has no seed to take
    res = cutfem.run("mean-curvature-meshed", levels=[16, 32, 64, 128], family=family, tau_e=0.1, solver="direct", **seed)
    assert _fit(res, "discrete_error") >= 1.0
    assert _fit(res, "l2_error") >= 1.0
    _assert_zero_integral(res)


def test_torus_meshed_unstabilized_structured_superconverges_flipped_fails():
    levels = [16, 32, 64, 128]
    s = cutfem.run("mean-curvature-meshed", levels=levels, family="structured", tau_e=0.0, solver="direct")
    f = cutfem.run("mean-curvature-meshed", levels=levels, family="flipped", tau_e=0.0, seed=3, solver="direct")
    # structured: about 2 in the discrete norm (the paper's superconvergence)
    assert 1.8 <= s.rates["discrete_error"][-1] <= 2.2
    # flipped: no convergence; the error at the finest level is still of the order of the coarsest,
    # more than ten times the structured one, and the last rate is below 0.5
    ef = [r["discrete_error"] for r in f.records]
    assert ef[-1] > 0.5 * ef[0]
    assert f.rates["discrete_error"][-1] < 0.5
    assert ef[-1] > 10 * s.records[-1]["discrete_error"]
    _assert_zero_integral(s)
    _assert_zero_integral(f)


def test_stabilization_keeps_zero_integral_and_changes_solution():
    a = cutfem.run("mean-curvature-meshed", levels=[32], family="flipped", tau_e=0.0, seed=1)
    b = cutfem.run("mean-curvature-meshed", levels=[32], family="flipped", tau_e=1.0, seed=1)
    _assert_zero_integral(a)
    _assert_zero_integral(b)
    assert abs(a.records[0]["discrete_error"] - b.records[0]["discrete_error"]) > 0.1


def test_torus_cut_stabilized_rate_at_least_one():
    res = cutfem.run("mean-curvature-cut", levels=[0.2, 0.1, 0.05], tau_f=0.1)
    assert _fit(res, "l2_error") >= 1.0
    rec = res.records[-1]
    assert rec["active_tets"] > 0 and rec["interior_faces"] > rec["active_tets"]
    assert abs(rec["area"] - 4 * np.pi**2 * 0.5) < 0.02
    _assert_zero_integral(res)


def test_cut_unstabilized_is_reported_singular():
    from cutfem.solvers.diagnose import SolverError

    with pytest.raises(SolverError):
        cutfem.run("mean-curvature-cut", levels=[0.1], tau_f=0.0, solver="direct")


@pytest.mark.parametrize("problem,surface,levels", [
    ("laplace-beltrami-meshed", "sphere", [16, 32, 64]),
    ("laplace-beltrami-meshed", "torus", [16, 32, 64]),
    ("laplace-beltrami-cut", "sphere", [0.4, 0.2, 0.1]),
    ("laplace-beltrami-cut", "torus", [0.2, 0.1, 0.05]),
])
def test_laplace_beltrami_rates(problem, surface, levels):
    res = cutfem.run(problem, levels=levels, surface=surface)
    assert 1.7 <= _fit(res, "l2_error") <= 2.6
    assert 0.85 <= _fit(res, "h1_error") <= 1.4


def test_laplace_beltrami_cut_normal_gradient_stabilization():
    res = cutfem.run("laplace-beltrami-cut", levels=[0.4, 0.2, 0.1], surface="sphere", stabilization="normal")
    assert 1.7 <= _fit(res, "l2_error") <= 2.6
    assert 0.85 <= _fit(res, "h1_error") <= 1.4


def test_manufactured_data_against_finite_differences():
    """f = -Lap_S u + u from the closed forms agrees with a finite-difference Laplace-Beltrami."""
    from cutfem.problems.laplace_beltrami import SphereSolution, TorusSolution

    R, r = 1.0, 0.5
    sol = TorusSolution(R, r)
    t, p = np.meshgrid(np.linspace(0.1, 6, 7), np.linspace(-3, 3, 7))
    t, p = t.ravel(), p.ravel()

    def X(t, p):
        s = R + r * np.cos(p)
        return np.stack([s * np.cos(t), s * np.sin(t), r * np.sin(p)], axis=-1)

    d = 1e-4
    U = lambda t, p: sol.u(X(t, p))  # noqa: E731
    s = R + r * np.cos(p)
    sp = lambda p: R + r * np.cos(p)  # noqa: E731
    d_p = lambda p: (sp(p + d / 2) * (U(t, p + d) - U(t, p)) - sp(p - d / 2) * (U(t, p) - U(t, p - d))) / d**2  # noqa: E731
    lap = d_p(p) / (r**2 * s) + (U(t + d, p) - 2 * U(t, p) + U(t - d, p)) / d**2 / s**2
    assert np.allclose(sol.f(X(t, p)), -lap + U(t, p), atol=1e-5)
    # sphere: u = xy + z, Lap_S by the same construction in spherical angles
    sph = SphereSolution(1.0)
    th, ph = np.meshgrid(np.linspace(0.3, 2.8, 6), np.linspace(0, 6, 6))
    th, ph = th.ravel(), ph.ravel()
    Y = lambda th, ph: np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=-1)  # noqa: E731
    V = lambda th, ph: sph.u(Y(th, ph))  # noqa: E731
    lap = ((np.sin(th + d / 2) * (V(th + d, ph) - V(th, ph)) - np.sin(th - d / 2) * (V(th, ph) - V(th - d, ph))) / d**2) / np.sin(th)
    lap += (V(th, ph + d) - 2 * V(th, ph) + V(th, ph - d)) / d**2 / np.sin(th) ** 2
    assert np.allclose(sph.f(Y(th, ph)), -lap + V(th, ph), atol=1e-5)
    # tangential gradients against finite differences along the surface
    x = X(t, p)
    g = sol.grad(x)
    dt = (U(t + d, p) - U(t - d, p)) / (2 * d)
    xt = (X(t + d, p) - X(t - d, p)) / (2 * d)
    assert np.allclose(np.einsum("ij,ij->i", g, xt), dt, atol=1e-6)


def test_manufactured_solutions_are_extended_along_the_normals():
    """u, f and grad_S u at a point off the surface equal their values at its closest point
    (the extension f^e = f o p of docs/math.md §4); the torus's compiled angles agree with
    numpy's arctan2 and trigonometric functions; the angles' singular set is an error."""
    from cutfem.geometry.shapes import Sphere, Torus
    from cutfem.problems.laplace_beltrami import manufactured
    from cutfem.runs.registry import ProblemError

    rng = np.random.default_rng(7)
    for phi in (Torus(1.0, 0.5), Sphere(1.3)):
        sol = manufactured(phi)
        x = rng.uniform(-1.4, 1.4, (200, 3))
        x = x[np.abs(phi.value(x)) < 0.2]
        p = phi.closest_point(x)
        for fn in (sol.u, sol.f, sol.grad):
            np.testing.assert_allclose(fn(x), fn(p), rtol=0, atol=1e-13)
    sol = manufactured(Torus(1.0, 0.5))
    t, q = rng.uniform(-np.pi, np.pi, (2, 50))
    s = 1.0 + 0.5 * np.cos(q)
    on = np.stack([s * np.cos(t), s * np.sin(t), 0.5 * np.sin(q)], axis=-1)
    np.testing.assert_allclose(sol.u(on), np.cos(3 * t) * np.sin(q), rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match="axis or its core circle"):
        sol.u(np.array([[0.0, 0.0, 0.3], [1.0, 0.0, 0.0]]))
    with pytest.raises(ProblemError, match="centre 0"):
        manufactured(Torus(1.0, 0.5, center=(0.1, 0, 0)))


def test_bad_parameters_are_reported():
    from cutfem.runs.registry import ProblemError

    with pytest.raises(ProblemError, match="allowed"):
        cutfem.run("mean-curvature-cut", levels=[0.2], tau=0.1)
    with pytest.raises(ProblemError, match=">= 0"):
        cutfem.run("mean-curvature-cut", levels=[0.2], tau_f=-1.0)
    with pytest.raises(ProblemError, match="available"):
        cutfem.run("no-such-problem")
    with pytest.raises(ProblemError, match="family"):
        cutfem.run("mean-curvature-meshed", levels=[8], family="zigzag")


# ----------------------------------------------------------------------------------------------
# units of length: the stabilization's weight is a number in units of --length-scale L
# ----------------------------------------------------------------------------------------------


def _mean_curvature_field(res):
    return np.asarray(res.records[0]["fields"]["surface"].point_data["H_h"])


def _scaled_sphere_file(tmp_path, scale):
    from cutfem.geometry.surface import SurfaceMesh, write_surface
    from cutfem.geometry.surface_meshes import sphere_mesh

    mesh = sphere_mesh(2)
    path = tmp_path / f"sphere_{scale:g}.stl"
    write_surface(SurfaceMesh(scale * np.asarray(mesh.points), mesh.triangles), path)
    return path


def test_meshed_mean_curvature_of_a_file_scales_exactly_with_its_unit(tmp_path):
    # the unit sphere mesh given in metres, and the same sphere as 1 mm given in metres with L = 1 mm:
    # H_h scales as 1/L, so H_h * 1e-3 of the second is H_h of the first (before: H . n R = 2.9e-6 for
    # the millimetre sphere at level 3, against 2.01 for the unit sphere)
    unit = cutfem.run("mean-curvature-meshed", levels=[1], surface=str(_scaled_sphere_file(tmp_path, 1.0)), solver="direct")
    milli = cutfem.run("mean-curvature-meshed", levels=[1], surface=str(_scaled_sphere_file(tmp_path, 1e-3)),
                       length_scale=1e-3, solver="direct")
    H1, Hm = _mean_curvature_field(unit), _mean_curvature_field(milli)
    np.testing.assert_allclose(Hm * 1e-3, H1, rtol=0, atol=1e-9 * np.abs(H1).max())
    assert np.abs(np.linalg.norm(H1, axis=1) - 2.0).max() < 0.1


@pytest.mark.parametrize("radius", [0.01, 100.0])
def test_meshed_mean_curvature_refuses_a_surface_far_from_the_length_scale(tmp_path, radius):
    path = _scaled_sphere_file(tmp_path, radius)
    with pytest.raises(ProblemError, match=rf"times the length scale L = 1 of the stabilization.*"
                       rf"--length-scale {radius:g} "):
        cutfem.run("mean-curvature-meshed", levels=[1], surface=str(path))


def test_cut_mean_curvature_scales_exactly_with_the_unit():
    # a sphere of radius 100 on a grid of spacing 40 with L = 100, against radius 1, spacing 0.4
    # (before, with L = 1: l2_error * R / sqrt(area) = 0.69 at radius 100, spacing 10; 0.0054 at radius 1)
    one = cutfem.run("mean-curvature-cut", levels=[0.4], surface="sphere", radius=1.0, solver="direct").records[0]
    big = cutfem.run("mean-curvature-cut", levels=[40.0], surface="sphere", radius=100.0, length_scale=100.0,
                     solver="direct").records[0]
    assert big["l2_error"] == pytest.approx(one["l2_error"], rel=1e-8)  # ||H||_{L2(S)} ~ (1/R) R: no unit
    with pytest.raises(ProblemError, match=r"--length-scale 100"):
        cutfem.run("mean-curvature-cut", levels=[40.0], surface="sphere", radius=100.0)


@pytest.mark.parametrize("stabilization, given, flag, wanted", [
    ("face", {"tau_n": 1e300}, "--tau-n", "normal"),
    ("face", {"normal_h_power": 0.0}, "--normal-h-power", "normal"),
    ("auto", {"tau_n": 2.0}, "--tau-n", "normal"),
    ("normal", {"tau_f": 5.0}, "--tau-f", "auto or face"),
    ("normal", {"face_h_power": 2.0}, "--face-h-power", "auto or face"),
    ("none", {"tau_f": 5.0}, "--tau-f", "auto or face"),
    ("none", {"tau_n": 5.0}, "--tau-n", "normal"),
])
def test_laplace_beltrami_cut_refuses_the_parameters_of_another_stabilization(stabilization, given, flag, wanted):
    """A parameter of the stabilization that is not chosen changes nothing: refused, not ignored
    (tau_n = 1e300 with the face term once ran and reported the face term's errors)."""
    from cutfem.runs.registry import ProblemError

    with pytest.raises(ProblemError) as e:
        cutfem.run("laplace-beltrami-cut", levels=[0.4], stabilization=stabilization, **given)
    assert str(e.value) == (f"{flag} applies only with --stabilization {wanted}, not with --stabilization "
                            f"'{stabilization}': leave {flag} out, or choose --stabilization {wanted.split()[0]}")


def test_laplace_beltrami_cut_records_only_the_chosen_stabilization_parameters():
    res = cutfem.run("laplace-beltrami-cut", levels=[0.4], stabilization="normal", tau_n=2.0)
    p = res.parameters
    assert p["tau_n"] == 2.0 and p["normal_h_power"] == 1.0
    assert "tau_f" not in p and "face_h_power" not in p


@pytest.mark.parametrize("problem", ["laplace-beltrami-meshed", "mean-curvature-meshed"])
def test_meshed_sphere_refuses_levels_that_give_the_same_mesh(problem):
    """The sphere's n is rounded to an icosahedron refined L = round(log2(n / 5)) times: n = 16 and
    20 both gave the mesh of 162 nodes, two equal rows under two names and no rate."""
    from cutfem.runs.registry import ProblemError

    with pytest.raises(ProblemError) as e:
        cutfem.run(problem, levels=[16, 20, 40], surface="sphere")
    assert str(e.value) == ("--n 16 and 20 give the same sphere mesh (the icosahedron refined 2 times, 162 nodes): "
                            "the sphere's n is rounded to 5 * 2^L; give levels that differ by a factor 2, e.g. 10 20 40 80")
    res = cutfem.run(problem, levels=[10, 20], surface="sphere")
    assert [r["dofs"] for r in res.records] == [42, 162]


@pytest.mark.parametrize("problem, level, params, words", [
    # the constants are seen by the mass term and not by the edge term, at 1e300: too strong
    ("laplace-beltrami-meshed", 16, {"tau_e": 1e300}, "because it is over-stabilized"),
])
def test_laplace_beltrami_names_a_stabilization_too_weak_or_too_strong(problem, level, params, words):
    """A numerically singular system from an extreme stabilization parameter says which way to
    move it; before, the solver could only list both possibilities (it did not know the
    stabilization matrix).  (tau_F at 1e-12 and 1e300 and tau_N at 1e300 no longer reach the
    solver: the problem refuses them first, naming the flag and its range, see the next test.)"""
    from cutfem.solvers.diagnose import SolverError

    with pytest.raises(SolverError) as e:
        cutfem.run(problem, levels=[level], **params)
    assert words in str(e.value)


@pytest.mark.parametrize("params, words, fit", [
    ({"tau_f": 1e-12}, "--tau-f 1e-12: tau_F = 1e-12 is below 1e-06: the face stabilization vanishes beside the mass of "
     "the pieces", "give tau_F in [0.001, 1.6e+05]"),
    ({"tau_f": 1e300}, "--tau-f 1e+300: tau_F = 1e+300 is 10^300.8 times (s / L)^2, the scale of the mass of a piece, "
     "above 1e+06 times", "give tau_F in [0.001, 1.6e+05]"),
    ({"stabilization": "normal", "tau_n": 1e300}, "--tau-n 1e+300: tau_N = 1e+300 is above 1e+06: the surface terms are "
     "lost beside it", "give tau_N in [0.01, 1e+02]"),
])
def test_laplace_beltrami_refuses_a_stabilization_out_of_its_range(params, words, fit):
    from cutfem.runs.registry import ProblemError

    with pytest.raises(ProblemError) as e:
        cutfem.run("laplace-beltrami-cut", levels=[0.4], **params)
    assert words in str(e.value) and fit in str(e.value)


def test_the_default_box_is_the_same_at_every_level_and_anchored_where_asked():
    """The default background box is the surface's box grown by 0.1 at every spacing (the unit
    sphere: [-1.1, 1.1]^3 at 0.2 and 0.1 alike; rounded to multiples of each spacing it was
    [-1.2, 1.2]^3 at 0.2 and the first rate read 2.47 for an error that fell by 4.10), so that
    h = N**(-1/3) halves with the spacing up to the node count (cells + 1 a side).  anchored=True
    puts the grid's nodes at multiples of the spacing, fixed in space for a moved surface."""
    from cutfem.geometry.shapes import Sphere
    from cutfem.problems.common import box_for

    res = cutfem.run("poisson-cut", levels=[0.2, 0.1])
    boxes = [r["box"] for r in res.records]
    np.testing.assert_allclose(boxes[0], [[-1.1] * 3, [1.1] * 3], atol=1e-12)
    np.testing.assert_allclose(boxes[1], boxes[0], atol=1e-12)
    assert [r["background_nodes"] for r in res.records] == [12**3, 23**3]
    assert res.rates["l2_error"][0] == pytest.approx(np.log(res.records[0]["l2_error"] / res.records[1]["l2_error"]) / np.log(23 / 12))
    lo, hi = box_for(Sphere(1.0, center=(0.013, -0.27, 0.5)), 0.1, anchored=True)
    np.testing.assert_allclose(lo, [-1.1, -1.4, -0.6], atol=1e-12)  # multiples of 0.1 outside the grown box
    np.testing.assert_allclose(hi, [1.2, 0.9, 1.6], atol=1e-12)
