"""The cutfem command, as a user would use it."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import cutfem
from cutfem.runs.cli import main
from cutfem.runs.registry import ProblemError, register

ROOT = Path(__file__).resolve().parents[2]


def test_list_shows_the_four_problems(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for name in ["mean-curvature-meshed", "mean-curvature-cut", "laplace-beltrami-meshed", "laplace-beltrami-cut"]:
        assert name in out
    assert main(["list", "-v"]) == 0
    out = capsys.readouterr().out
    assert "--tau-f" in out and "--face-h-power" in out and "--family" in out


def test_run_json_to_stdout_parses_with_documented_fields(capsys):
    assert main(["run", "mean-curvature-cut", "--spacing", "0.2", "0.1", "--json", "-"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["problem"] == "mean-curvature-cut"
    assert data["parameters"]["tau_f"] == 0.1 and data["parameters"]["face_h_power"] == 0.0
    assert data["levels"] == [0.2, 0.1]
    assert set(data["versions"]) >= {"cutfem", "numpy", "scipy", "python"}
    for rec in data["records"]:
        for key in ["h", "dofs", "active_tets", "pieces", "interior_faces", "l2_error", "area", "integral_H", "time", "spacing"]:
            assert key in rec, key
        assert set(rec["time"]) == {"geometry", "assembly", "solve", "errors"}
        assert len(rec["integral_H"]) == 3
    assert len(data["rates"]["l2_error"]) == 1 and data["rates"]["l2_error"][0] > 1.0


def test_run_writes_json_vtk_and_plot(tmp_path, capsys):
    js, vtk, png = tmp_path / "r.json", tmp_path / "vtk", tmp_path / "c.png"
    code = main(["run", "mean-curvature-meshed", "--family", "flipped", "--levels", "8", "16", "--json", str(js), "--vtk", str(vtk), "--plot", str(png), "--quiet"])
    assert code == 0
    out = capsys.readouterr().out
    assert "discrete_error" in out and "rate" in out
    assert json.loads(js.read_text())["parameters"]["family"] == "flipped"
    files = sorted(p.name for p in vtk.iterdir())
    assert files == ["mean-curvature-meshed_n16_surface.vtp", "mean-curvature-meshed_n8_surface.vtp", "mean-curvature-meshed_surface.pvd"]
    import pyvista as pv

    poly = pv.read(vtk / files[0])
    assert poly.point_data["H_h"].shape == (poly.n_points, 3)
    # the levels as one series, in order, readable by ParaView's (and pyvista's) .pvd reader
    series = pv.get_reader(vtk / files[2])
    assert series.time_values == [0.0, 1.0]
    assert [d.path for d in series.datasets] == ["mean-curvature-meshed_n8_surface.vtp", "mean-curvature-meshed_n16_surface.vtp"]
    assert png.stat().st_size > 5000


def test_bulk_fields_in_vtk_carry_phi_h_and_the_cut_marker(tmp_path):
    """A bulk problem's fields: u_h and u_exact on its element set with phi_h and the cut marker, and
    the interface surface; the unstructured grid is readable by meshio too."""
    import meshio
    import pyvista as pv

    assert main(["run", "poisson-cut", "--spacing", "0.4", "--vtk", str(tmp_path), "--quiet"]) == 0
    grid = pv.read(tmp_path / "poisson-cut_spacing0.4_domain.vtu")
    assert {"u_h", "u_exact", "phi_h"} <= set(grid.point_data.keys()) and "cut" in grid.cell_data.keys()
    assert grid.point_data["phi_h"].min() < 0 and 0 < grid.cell_data["cut"].sum() < grid.n_cells
    mesh = meshio.read(tmp_path / "poisson-cut_spacing0.4_domain.vtu")
    assert len(mesh.points) == grid.n_points and "u_h" in mesh.point_data
    assert (tmp_path / "poisson-cut_domain.pvd").exists() and (tmp_path / "poisson-cut_boundary.pvd").exists()


def test_cut_mean_curvature_vtk_holds_the_solution_at_its_points(tmp_path):
    """mean-curvature-cut --vtk on the unit sphere, checked against what the fields should be: the
    surface is S_h (area 1^T M 1 of the record), H_h on it is the trace of the active mesh's P1 H_h,
    H_exact = 2 x / |x|, mean_curvature = H_h . n with n the normalized sum of the unit normals of
    the triangles at a vertex (outward: 2 / R = 2 up to the discretization), the active mesh has the
    record's active tets of volume spacing^3 / 6 each."""
    import pyvista as pv

    js = tmp_path / "r.json"
    assert main(["run", "mean-curvature-cut", "--surface", "sphere", "--levels", "0.4", "--vtk", str(tmp_path), "--json", str(js),
                 "--quiet"]) == 0
    rec = json.loads(js.read_text())["records"][0]
    surface = pv.read(tmp_path / "mean-curvature-cut_spacing0.4_surface.vtp")
    active = pv.read(tmp_path / "mean-curvature-cut_spacing0.4_active_mesh.vtu")
    tri, x = surface.faces.reshape(-1, 4)[:, 1:], surface.points
    cross = np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]])
    assert 0.5 * np.linalg.norm(cross, axis=1).sum() == pytest.approx(rec["area"], rel=1e-12)
    assert active.n_cells == rec["active_tets"] and active.n_points == rec["dofs"]
    assert active.volume == pytest.approx(rec["active_tets"] * 0.4**3 / 6, rel=1e-12)
    probe = surface.sample(active, tolerance=1e-9)
    assert probe.point_data["vtkValidPointMask"].all()
    np.testing.assert_allclose(probe.point_data["H_h"], surface.point_data["H_h"], rtol=0, atol=1e-12)
    H = surface.point_data["H_h"]
    np.testing.assert_allclose(surface.point_data["H_exact"], 2 * x / np.linalg.norm(x, axis=1)[:, None], rtol=0, atol=1e-12)
    unit = cross / np.linalg.norm(cross, axis=1)[:, None]
    n = np.zeros_like(x)
    for k in range(3):
        np.add.at(n, tri[:, k], unit)
    n /= np.linalg.norm(n, axis=1)[:, None]
    np.testing.assert_allclose(surface.point_data["mean_curvature"], np.einsum("ij,ij->i", H, n), rtol=0, atol=1e-5)  # float32 normals
    assert np.all(np.abs(surface.point_data["mean_curvature"] - 2) < 0.2)
    np.testing.assert_allclose(surface.point_data["error"], np.linalg.norm(surface.point_data["H_exact"] - H, axis=1), rtol=1e-12)


@pytest.mark.parametrize("argv,pattern", [
    (["run", "nope"], "unknown problem 'nope'; available:"),
    (["run", "mean-curvature-cut", "--tau-f", "-1"], "--tau-f: -1.0 must be a finite number >= 0"),
    (["run", "mean-curvature-cut", "--tau-f", "abc"], "cannot read 'abc' as float"),
    (["run", "mean-curvature-cut", "--bogus", "3"], "unknown argument.*allowed: --levels"),
    (["run", "mean-curvature-cut", "--surface", "sphere", "--radius", "3", "--box", "-1,-1,-1,1,1,1", "--levels", "0.25"], "surface reaches or leaves the box"),
    (["run", "mean-curvature-cut", "--surface", "sphere", "--radius", "0.01", "--box", "-1,-1,-1,1,1,1", "--levels", "0.25"], "too coarse to resolve the surface"),
    (["run", "mean-curvature-cut", "--surface", "sphere", "--radius", "0.01", "--box", "0.3,0.3,0.3,1,1,1", "--levels", "0.1"], "does not cut the background mesh"),
    (["run", "mean-curvature-meshed", "--surface", "missing.stl"], "--surface: 'missing.stl' is neither torus, sphere nor an existing file"),
    (["run", "laplace-beltrami-cut", "--stabilization", "n.a"], "--stabilization: 'n.a' is not one of auto, face, normal, none"),
    (["run", "laplace-beltrami-meshed", "--surface", "ball.stl"], "--surface: 'ball.stl' is not one of torus, sphere"),
    (["run", "heat-surface-cut", "--theta", "0.7"], r"--theta: 0.7 is not one of 1.0, 0.5"),
    (["run", "mean-curvature-cut", "--face-h-power", "nan"], "--face-h-power: nan is not a finite number"),
    (["run", "heat-surface-cut", "--theta", "inf"], "--theta: inf is not a finite number"),
    (["run", "mean-curvature-cut", "--surface", "nosuch.stl", "--levels", "0.2"], "there is no file 'nosuch.stl'"),
    (["run", "mean-curvature-cut", "--surface", "ellipsoid", "--axes", "1,0,0.5", "--levels", "0.2"], "--axes 1,0,0.5: b must be"),
    (["run", "mean-curvature-meshed", "--seed", "-1", "--levels", "8"], "--seed: -1 must be a finite number >= 0"),
    (["run", "mean-curvature-meshed", "--seed", "3", "--levels", "8"], "--seed applies only with --family flipped or perturbed or perturbed-flipped, not with --family 'structured'"),
    (["run", "poisson-cut", "--gamma", "0", "--levels", "0.2"], "--gamma: 0.0 must be a positive number"),
    (["run", "interface-poisson-cut", "--a-outside", "0", "--levels", "0.2"], "--a-outside: 0.0 must be a positive number"),
    (["run", "bulk-surface-cut", "--c-bulk", "0", "--levels", "0.2"], "--c-bulk: 0.0 must be a positive number"),
    (["run", "mean-curvature-meshed", "--length-scale", "0", "--levels", "8"], "--length-scale: 0.0 must be a positive number"),
    (["run", "mean-curvature-cut", "--surface", "sphere", "--radius", "0", "--levels", "0.2"], "--radius: 0.0 must be a positive number"),
    (["run", "mean-curvature-cut", "--radius", "2", "--levels", "0.2"], "--radius applies only with --surface sphere, not with --surface 'torus'"),
    (["run", "mean-curvature-meshed", "--surface", "sphere", "--family", "flipped"], "--family applies only with --surface torus"),
    (["run", "laplace-beltrami-cut", "--axes", "1,1,1"], "unknown argument.*--axes"),
    (["run", "mean-curvature-cut", "--levels", "0.2", "--spacing", "0.1"], "--spacing: not allowed with argument --levels"),
    (["run", "poisson-cut", "--gamma-g", "0", "--levels", "0.2"], r"indefinite.*raise the Nitsche penalty \(gamma 10 .* or add a ghost penalty \(the form has none"),
    (["run", "mean-curvature-cut", "--levels", "0.1", "--tau-f", "0", "--solver", "direct"], "singular"),
])
def test_bad_input_is_one_line_and_exit_2(argv, pattern, capsys):
    assert main(argv + ["--quiet"] if argv[0] == "run" and len(argv) > 2 else argv) == 2
    err = capsys.readouterr().err
    assert re.search(pattern, err), err
    assert "Traceback" not in err


def test_open_surface_file_is_reported(tmp_path, capsys):
    from cutfem.geometry.surface_meshes import sphere_mesh

    m = sphere_mesh(1)
    tris = m.triangles[1:]  # drop one triangle: the surface is open
    import meshio

    path = tmp_path / "open.stl"
    meshio.write(path, meshio.Mesh(m.points, [("triangle", tris)]))
    assert main(["run", "mean-curvature-meshed", "--surface", str(path), "--quiet"]) == 2
    assert "open" in capsys.readouterr().err


def test_closed_surface_file_runs(tmp_path, capsys):
    from cutfem.geometry.surface_meshes import sphere_mesh
    from cutfem.geometry.surface import write_surface

    path = tmp_path / "ball.obj"
    write_surface(sphere_mesh(3, radius=1.5), path)
    assert main(["run", "mean-curvature-meshed", "--surface", str(path), "--json", "-"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["levels"] == [1]  # one resolution: one level, not the torus's four
    rec = data["records"][0]
    assert abs(rec["area"] - 4 * np.pi * 1.5**2) < 0.2
    assert np.max(np.abs(rec["integral_H"])) < 1e-9
    assert main(["run", "mean-curvature-meshed", "--surface", str(path), "--levels", "16", "32", "--quiet"]) == 2
    assert "a mesh file is solved as it is" in capsys.readouterr().err


def test_console_script_is_installed():
    out = subprocess.run([sys.executable, "-m", "cutfem.runs.cli", "list"], capture_output=True, text=True, check=True).stdout
    assert "mean-curvature-cut" in out


def test_console_entry_exits_with_the_command_status():
    """The console script's entry passes main's status to the process: 0 for a run, 2 for bad input
    (one line, no traceback)."""
    run = subprocess.run([sys.executable, "-m", "cutfem.runs.cli", "run", "mean-curvature-cut", "--spacing", "0.2", "--quiet"],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert "0.2" in run.stdout and "Traceback" not in run.stderr
    bad = subprocess.run([sys.executable, "-m", "cutfem.runs.cli", "run", "no-such-problem"], capture_output=True, text=True)
    assert bad.returncode == 2
    assert "no-such-problem" in bad.stderr and "Traceback" not in bad.stderr


def test_readme_examples_run():
    """Every python block of the README runs (the worked Helmholtz example reaches rate ~2)."""
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert len(blocks) >= 2
    ns = {}
    for block in blocks:
        exec(compile(block, "README.md", "exec"), ns)
    result = ns["result"]
    assert result.rates["l2_error"][-1] > 1.8


def _forms_md_blocks():
    return re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "forms.md").read_text(), re.S)


def test_forms_md_examples_run_and_mean_what_they_say():
    """Every python block of docs/forms.md runs as shown, given only the names its text leaves to
    the reader (data f, g, coefficients, the state of a time step), and computes what the page says:
    the Nitsche block is the formula above it (a user integrand assembles the same matrix and vector)
    and reproduces a linear u exactly on either side, the interface block reproduces a linear u, the
    coupling integrand is interface_nitsche, the bulk-surface form has the kernel (1/b_B, 1/b_S) of
    docs/math.md §10 at c_B = 0, the heat steps keep the integral of u_h following the source, the
    elasticity block converges to its exact displacement by CG with the multigrid, and the
    multiplier's row is the integrals of the basis functions."""
    from cutfem.geometry.cut import CUT, NEG, POS, cut_mesh
    from cutfem.fem.exact import Exact
    from cutfem.fem.forms import assemble, bilinear_form, linear_form
    from cutfem.fem.norms import l2_error
    from cutfem.fem.pointwise import dot
    from cutfem.fem.terms import (apply_dirichlet, basis_integrals, face_jump_penalty, interface_nitsche, load, nitsche,
                                  stiffness)
    from cutfem.geometry.csg import intersection
    from cutfem.geometry.shapes import Plane, Sphere
    from cutfem.geometry.box import structured_box
    from cutfem.solvers.solve import solve
    from cutfem.fem.spaces import CutSpace
    from cutfem.geometry.surface_meshes import sphere_mesh

    blocks = _forms_md_blocks()
    assert len(blocks) == 9
    ns = {}
    exec("from cutfem.geometry.cut import CUT, NEG, POS, cut_mesh\n"
         "from cutfem.fem.forms import *\n"
         "from cutfem.fem.pointwise import *\n"
         "from cutfem.fem.terms import *\n"
         "from cutfem.fem.elasticity import *\n"
         "from cutfem.fem.coupling import *\n"
         "from cutfem.fem.exact import Exact\n"
         "from cutfem.solvers.krylov import CGSolver\n"
         "from cutfem.solvers.direct import DirectSolver\n"
         "from cutfem.solvers.solve import solve\n"
         "from cutfem.fem.spaces import CutSpace, ProductSpace, RealSpace, VectorSpace\n"
         "from cutfem.problems.heat_surface import extrapolated\n", ns)

    def run(k, **context):
        ns.update(context)
        exec(compile(blocks[k], f"docs/forms.md, block {k}", "exec"), ns)

    g = np.array([0.3, -0.7, 0.5])
    linear = lambda x: x @ g + 0.25  # noqa: E731
    zero = lambda x: np.zeros(x.shape[:2])  # noqa: E731

    # the pieces
    run(0, background=structured_box([-1.2] * 3, [1.2] * 3, spacing=0.3), phi=Sphere(1.0), mesh=sphere_mesh(2))
    cut = ns["cut"]
    centroids = cut.triangle_points.mean(axis=1)
    assert np.all(np.einsum("md,md->m", cut.normals[cut.triangle_tets], centroids) > 0)  # n_h from NEG (inside) to POS
    assert len(ns["W"].split(np.arange(ns["W"].n_dofs))) == 2

    # fictitious-domain Poisson: the block is the formula above it, and a linear u is reproduced
    run(1, f=zero, g=linear)
    V, K, b = ns["V"], ns["K"], ns["b"]

    @bilinear_form(symmetric=True)
    def a(u, v, w):
        return -dot(w.n, u.grad) * v - dot(w.n, v.grad) * u + 10.0 / w.h * u * v

    @linear_form
    def l(v, w):
        return w.at(linear) * (10.0 / w.h * v - dot(w.n, v.grad))

    dx, ds, ghost = cut.dx(NEG), cut.ds(), 0.1 * face_jump_penalty(cut.dF(cut.ghost_facets(NEG)), h_power=1)
    K_user = assemble(stiffness(dx) + a * ds + ghost, V)
    assert abs(K - K_user).max() <= 1e-12 * abs(K).max()
    assert np.abs(b - assemble(l * ds, V)).max() <= 1e-12 * np.abs(b).max()
    u, _ = solve(K, b, method="direct")
    assert np.abs(u - linear(V.dof_points)).max() < 1e-9

    # ... and outside Gamma: nitsche takes -n_h, a user integrand writes the sign itself
    Vp, dxp = CutSpace(cut, POS), cut.dx(POS)

    @bilinear_form(symmetric=True)
    def a_pos(u, v, w):
        return dot(w.n, u.grad) * v + dot(w.n, v.grad) * u + 10.0 / w.h * u * v

    ghost_pos = 0.1 * face_jump_penalty(cut.dF(cut.ghost_facets(POS)), h_power=1)
    N = nitsche(ds, gamma=10, g=linear)
    Kp = assemble(stiffness(dxp) + N + ghost_pos, Vp)
    assert abs(Kp - assemble(stiffness(dxp) + a_pos * ds + ghost_pos, Vp)).max() <= 1e-12 * abs(Kp).max()
    bp = assemble(load(zero, dxp) + N.load, Vp)
    box = Vp.boundary_dofs
    u, _ = solve(*apply_dirichlet(Kp, bp, box, linear(Vp.dof_points[box])), method="direct")
    assert np.abs(u - linear(Vp.dof_points)).max() < 1e-9

    # interface problem, a = 2 on both sides: a linear u on both fields
    W0 = ns["W"][1]
    rhs = load(zero, cut.dx(NEG), field=0) + load(zero, cut.dx(POS), field=1)
    run(2, a_neg=2.0, a_pos=2.0, a={NEG: 2.0, POS: 2.0}, rhs=rhs, g_values=linear(W0.dof_points[W0.boundary_dofs]))
    W = ns["W"]
    x, _ = solve(ns["K"], ns["b"], method="direct")
    for field, u in zip(W.fields, W.split(x)):
        assert np.abs(u - linear(field.dof_points)).max() < 1e-9

    # the coupling integrand is interface_nitsche with the harmonic weights
    a_neg, a_pos, gamma = 1.0, 3.0, 10.0
    k_neg = a_pos / (a_neg + a_pos)
    k_pos = 1.0 - k_neg
    run(3, a_neg=a_neg, a_pos=a_pos, k_neg=k_neg, k_pos=k_pos, lam=2 * gamma * (k_neg**2 * a_neg + k_pos**2 * a_pos))
    C = assemble(interface_nitsche(ds, a_neg, a_pos, gamma=gamma, weights="harmonic"), W)
    assert abs(C - assemble(ns["coupling"] * ds, W)).max() <= 1e-12 * abs(C).max()

    # bulk-surface coupling: at c_B = 0 the constants (1/b_B, 1/b_S) are its kernel
    run(4, b_b=1.5, b_s=2.0, k_b=1.0, k_s=0.5, c_b=0.0)
    Wb = ns["W"]
    K = assemble(ns["form"], Wb)
    kernel = Wb.join([np.full(Wb["bulk"].n_dofs, 1 / 1.5), np.full(Wb["surface"].n_dofs, 1 / 2.0)])
    assert abs(K - K.T).max() == 0
    assert np.abs(K @ kernel).max() < 1e-12 * abs(K).max()
    assert np.abs(K @ Wb.join([np.ones(Wb["bulk"].n_dofs), np.zeros(Wb["surface"].n_dofs)])).max() > 0.1

    # surface heat equation: a Crank-Nicolson step, then a backward Euler step by CG; the integral of
    # u_h follows the source, 1^T M u^n = 1^T M u^{n-1} + dt (theta 1^T F^n + (1 - theta) 1^T F^{n-1})
    Vc = CutSpace(cut, CUT)
    u0 = np.cos(Vc.dof_points[:, 0])
    F_new, F_old = assemble(load(linear, ds), Vc), assemble(load(lambda x: x[..., 2] + 1.0, ds), Vc)
    theta, dt = 0.5, 0.05
    run(5, tau=1.0, theta=theta, dt=dt, u=u0, F_new=F_new, F_old=F_old, history=[0.5 * u0, 0.8 * u0, u0])
    M, u = ns["M"], ns["u"]
    one = np.ones(Vc.n_dofs)
    expected = one @ M @ u0 + dt * (theta * F_new.sum() + (1 - theta) * F_old.sum()) + dt * F_new.sum()
    assert abs(one @ M @ u - expected) < 1e-10 * abs(expected)
    assert ns["info"].iterations > 0

    # elasticity on a vector field: the block's solution approaches the exact displacement
    fine = cut_mesh(structured_box([-1.2] * 3, [1.2] * 3, spacing=0.1), Sphere(1.0))
    ue, mu, lam = Exact(["sin(x)", "y * z", "cos(z)"]), 1.0, 2.0
    f = -(2 * mu * ue.sym_grad + lam * ue.div * Exact.identity()).div
    run(6, cut=fine, dx=fine.dx(NEG), ds=fine.ds(), mu=mu, lam=lam, u=ue, f=f)
    assert ns["info"].method == "cg-mg"
    assert l2_error(ns["W"], ns["x"], ue, fine.dx(NEG)) < 1.1 * 5.20e-3  # measured 5.20e-3 (17247 unknowns)

    # a multiplier: its row in the bordered matrix is (phi_i, 1)
    run(7, V=CutSpace(cut, NEG), dx=cut.dx(NEG), dg=cut.dF(cut.ghost_facets(NEG)))
    K, Vn = ns["K"], ns["V"]
    assert (K != K.T).nnz == 0 and K.shape == (Vn.n_dofs + 1,) * 2
    ones = assemble(basis_integrals(cut.dx(NEG)), Vn)
    assert np.abs(K[Vn.n_dofs, : Vn.n_dofs].toarray().ravel() - ones).max() < 1e-14 * ones.max()

    # a domain of two level sets: Nitsche on the sphere, the flux on the disc; a linear u exactly
    run(8, background=structured_box([-1.2] * 3, [1.2] * 3, spacing=0.3), intersection=intersection, ball=Sphere(1.0),
        cap=Plane((0, 0, 1), (0, 0, 0.5)), f=zero, g=linear, g_n=lambda x: np.full(x.shape[:-1], g[2]))
    u, _ = solve(ns["K"], ns["b"], method="direct")
    assert np.abs(u - linear(ns["V"].dof_points)).max() < 1e-9


def test_readme_commands_match_ci():
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    assert 'pip install -e ".[test]"' in readme and 'pip install -e ".[test]"' in ci
    assert "python -m pytest -q" in readme and "python -m pytest -q" in ci
    assert "cutfem reproduce" in readme


# ----------------------------------------------------------------------------------------------
# inputs checked before solving, sizes, failures that keep the finished levels, the JSON record
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("flag", ["--spacing", "--levels"])
@pytest.mark.parametrize("value", ["0", "nan", "-0.1", "inf", "abc"])
def test_bad_spacing_names_the_flag(flag, value, capsys):
    assert main(["run", "mean-curvature-cut", flag, "0.2", value, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"error: {flag}: spacing '{value}' is not a positive finite number" in err, err
    assert "box" not in err and "Traceback" not in err


def test_a_level_given_twice_is_refused(capsys, tmp_path):
    """A repeated level would compare a level with itself and write its VTK files twice under one
    name: refused before anything is solved, from the shell (0.2 and 0.20 are one level) and from
    Python."""
    assert main(["run", "mean-curvature-cut", "--spacing", "0.2", "0.20", "--vtk", str(tmp_path / "vtk"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "error: --spacing: spacing 0.2 is given more than once" in err, err
    assert not (tmp_path / "vtk").exists()
    with pytest.raises(ProblemError, match=r"^levels: n 16 is given more than once"):
        cutfem.run("mean-curvature-meshed", levels=[16, 32, 16])


def test_box_that_does_not_fit_the_spacing_is_grown_at_that_spacing(capsys):
    """--box of width 3 at spacing 0.4 (7.5 cells) is grown symmetrically to 8 cells, [-1.6, 1.6]^3;
    the spacing stays 0.4, so N = 9**3 background nodes and h = N**(-1/3) = 1/9."""
    assert main(["run", "mean-curvature-cut", "--surface", "sphere", "--box", "-1.5,-1.5,-1.5,1.5,1.5,1.5", "--spacing", "0.4", "--json", "-"]) == 0
    rec = json.loads(capsys.readouterr().out)["records"][0]
    np.testing.assert_allclose(rec["box"], [[-1.6] * 3, [1.6] * 3], atol=1e-14)
    assert rec["background_nodes"] == 9**3
    assert rec["h"] == pytest.approx(1 / 9, rel=1e-12)


def test_size_that_cannot_fit_is_refused_before_allocating(capsys):
    """Spacing 1e-4 on the torus (1.2e13 background nodes) is refused at once, in Python and on the
    command line, with the estimate, the memory available and the fix."""
    import time

    from cutfem.memory import InsufficientMemoryError

    t0 = time.perf_counter()
    with pytest.raises(InsufficientMemoryError, match=r"spacing 0.0001 .* needs about .*TiB of memory, more than the .* available .*coarser spacing"):
        cutfem.run("mean-curvature-cut", levels=[1e-4])
    assert main(["run", "mean-curvature-cut", "--spacing", "1e-4", "--quiet"]) == 2
    assert time.perf_counter() - t0 < 2.0
    err = capsys.readouterr().err
    assert "coarser spacing" in err and "Traceback" not in err


def test_memory_limit_refuses_the_band_and_the_matrices(monkeypatch):
    """With CUTFEM_MEMORY_LIMIT the cut is refused from the band estimate; a cut that fits but
    whose matrices would not is refused before the cut, from the active tets it predicts; and where
    no prediction is made (no Lipschitz bound) the real active tets are checked before the matrices
    are built.  (The spacings that these refusals name are checked in tests/test_memory.py.)"""
    from cutfem.memory import InsufficientMemoryError

    monkeypatch.setenv("CUTFEM_MEMORY_LIMIT", "20MiB")  # below the cut's fixed part, 150 MiB
    with pytest.raises(InsufficientMemoryError, match=r"cells near the surface\) needs about .* more than the 20 MiB available "
                       r"\(CUTFEM_MEMORY_LIMIT\); no spacing fits: the fixed part alone needs about 150 MiB"):
        cutfem.run("mean-curvature-cut", levels=[0.025])
    # spacing 0.05: the cut (14,024 band cells, 16,519 predicted; with the box's bitmap and boundary
    # 175 MB) fits in 200 MiB (210 MB); the 66,075 active tets it predicts (52,252 made) at 5000
    # bytes each on top of 64 MiB (397 MB) do not.  (The mean
    # curvature problem's 200 bytes a tet never exceed the band estimate of the same cut; the
    # per-tet cost is raised here to reach the second estimate.)
    monkeypatch.setattr("cutfem.problems.mean_curvature.BYTES_PER_ACTIVE_TET", 5000)
    monkeypatch.setenv("CUTFEM_MEMORY_LIMIT", "200MiB")
    with pytest.raises(InsufficientMemoryError, match=r"^the matrices and the solve of about 6.61e\+04 active tets \(predicted for the cut "
                       r"of the 64 x 64 x 24-cell box at spacing 0.05\) needs about 379 MiB .*; use a coarser spacing \(about 0.077 or more\)"):
        cutfem.run("mean-curvature-cut", levels=[0.05])
    # the ellipsoid declares no Lipschitz bound: its cut (every node evaluated, 48,285 nodes,
    # 177 MB) fits and its 21,596 active tets (at 10,000 bytes, 283 MB) are refused after the cut
    monkeypatch.setattr("cutfem.problems.mean_curvature.BYTES_PER_ACTIVE_TET", 10_000)
    with pytest.raises(InsufficientMemoryError, match=r"^the matrices and the solve of \d+ active tets needs about .*; use a coarser spacing \(about"):
        cutfem.run("mean-curvature-cut", levels=[0.05], surface="ellipsoid")
    with pytest.raises(InsufficientMemoryError, match=r"meshed torus at n = 4096"):
        cutfem.run("mean-curvature-meshed", levels=[4096])


def test_failing_last_level_keeps_the_finished_ones(tmp_path, capsys):
    """A spacing too coarse to cut the torus fails the last level: the table and the JSON keep the
    two finished levels and record the failure; the plot is drawn; the exit status is 2."""
    js, png = tmp_path / "out" / "r.json", tmp_path / "c.png"
    code = main(["run", "mean-curvature-cut", "--spacing", "0.2", "0.1", "5", "--json", str(js), "--plot", str(png), "--quiet"])
    assert code == 2
    out, err = capsys.readouterr()
    assert "spacing=5.0 failed (CutError)" in out and out.count("\n") >= 4
    assert "error: spacing=5.0 failed (2 finished level(s) kept)" in err
    data = json.loads(js.read_text())
    assert data["levels"] == [0.2, 0.1, 5.0] and [r["spacing"] for r in data["records"]] == [0.2, 0.1]
    assert data["failure"]["level"] == 5.0 and data["failure"]["index"] == 2
    assert data["failure"]["error_type"] == "CutError" and "does not cut" in data["failure"]["message"]
    assert len(data["rates"]["l2_error"]) == 1 and data["rates"]["l2_error"][0] > 1.0
    assert png.stat().st_size > 5000


def test_unexpected_error_in_a_level_exits_1(monkeypatch, tmp_path, capsys):
    problem = cutfem.get_problem("mean-curvature-meshed")
    monkeypatch.setattr(problem, "solve_level", lambda *a, **k: [][1])
    js = tmp_path / "r.json"
    assert main(["run", "mean-curvature-meshed", "--n", "8", "--json", str(js), "--quiet"]) == 1
    assert json.loads(js.read_text())["failure"]["error_type"] == "IndexError"
    assert "list index out of range" in capsys.readouterr().err


@pytest.mark.parametrize("flag,path,pattern", [
    ("--plot", "conv.txt", "should end in .png or .pdf or .svg"),
    ("--json", "out.csv", "should end in .json"),
    ("--json", "/proc/no/r.json", "is not writable"),
    ("--vtk", "/proc/cpuinfo", "is not a folder"),
    ("--json", "/proc/cpuinfo/r.json", "'/proc/cpuinfo' is a file, not a folder"),
    ("--vtk", "/proc/cpuinfo/sub/dir", "'/proc/cpuinfo' is a file, not a folder"),
])
def test_outputs_are_checked_before_solving(flag, path, pattern, monkeypatch, capsys):
    problem = cutfem.get_problem("mean-curvature-cut")
    monkeypatch.setattr(problem, "solve_level", lambda *a, **k: pytest.fail("solved before checking the outputs"))
    assert main(["run", "mean-curvature-cut", "--spacing", "0.2", flag, path, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"error: {flag}: " in err and re.search(pattern, err), err


def test_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"cutfem {cutfem.__version__}"
    out = subprocess.run([sys.executable, "-m", "cutfem.runs.cli", "--version"], capture_output=True, text=True, check=True).stdout
    assert out.strip() == f"cutfem {cutfem.__version__}"


def test_json_record_describes_itself(capsys):
    import scipy
    import threadpoolctl  # noqa: F401 - a dependency: the thread pools are recorded

    assert main(["run", "mean-curvature-cut", "--spacing", "0.2", "--json", "-"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["schema_version"] == cutfem.runs.runner.SCHEMA_VERSION == 2
    assert data["failure"] is None and data["level_name"] == "spacing"
    assert set(data["definitions"]) == {"h", "dofs", "l2_error", "area_error"}
    assert "N**(-1/3)" in data["definitions"]["h"] and "H^e" in data["definitions"]["l2_error"]
    assert data["components"] == 3 and data["dofs_per_component"] == [data["records"][0]["dofs"]]
    assert data["command"] == ["cutfem", "run", "mean-curvature-cut", "--spacing", "0.2", "--json", "-"]
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", data["created_utc"])
    assert data["git_commit"] is None or re.fullmatch(r"[0-9a-f]{40}", data["git_commit"])
    assert data["git_modified"] in ((None,) if data["git_commit"] is None else (True, False))
    assert data["threads"]["cpu_count"] >= 1 and isinstance(data["threads"]["pools"], list)
    numba_threads = data["threads"]["numba"]
    assert numba_threads["num_threads"] >= 1 and numba_threads["threading_layer"] in ("omp", "tbb", "workqueue")
    assert "omp_wait_policy" in numba_threads
    v = data["versions"]
    assert v["numpy"] == np.__version__ and v["scipy"] == scipy.__version__ and v["cutfem"] == cutfem.__version__
    assert v["pyvista"] and v["vtk"]


def test_vtk_of_a_problem_without_fields_says_nothing_was_written(tmp_path, capsys):
    @register("test-fieldless", levels=[0.5], level_name="step")
    def fieldless(step):
        return {"h": step}

    assert main(["run", "test-fieldless", "--vtk", str(tmp_path / "v"), "--quiet"]) == 0  # in-process: registered
    err = capsys.readouterr().err
    assert "nothing written" in err and "wrote VTK" not in err
    assert not any((tmp_path / "v").iterdir())


def test_heat_writes_its_fields(tmp_path):
    import pyvista as pv

    assert main(["run", "heat-surface-cut", "--levels", "0.4", "--vtk", str(tmp_path), "--quiet"]) == 0
    surface = pv.read(tmp_path / "heat-surface-cut_spacing0.4_surface.vtp")
    err = np.abs(surface.point_data["u_h"] - surface.point_data["u_exact"]).max()
    assert surface.n_points > 100 and 0 < err < 0.1 * np.abs(surface.point_data["u_exact"]).max()


def test_reproduce_is_a_command(capsys):
    """``cutfem reproduce`` reaches the studies' reproduce (cutfem.studies.reproduce)."""
    assert main(["reproduce", "--list"]) == 0
    assert "paper_meshed" in capsys.readouterr().out


def test_run_help_without_a_problem(capsys):
    assert main(["run", "--help"]) == 0
    assert "cutfem run PROBLEM" in capsys.readouterr().out


def test_using_cutfem_leaves_the_environment_alone():
    code = (
        "import os, numpy as np, scipy.sparse as sp\n"
        "before = dict(os.environ)\n"
        "import cutfem\n"
        "from cutfem.solvers.solve import solve\n"
        "A = sp.diags([2.0] * 50) - sp.diags([0.5] * 49, 1) - sp.diags([0.5] * 49, -1)\n"
        "solve(A.tocsr(), np.ones(50), method='direct')\n"
        "cutfem.run('mean-curvature-meshed', levels=[8]).to_json()\n"
        "after = dict(os.environ)\n"
        "print(sorted(set(before.items()) ^ set(after.items())))\n"
    )
    assert _fresh_python(code).strip() == "[]"


def _fresh_python(code: str) -> str:
    """The standard output of ``code`` run by a fresh interpreter (a process with nothing loaded)."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_studies_and_reproduce_check_their_output_folder_first(tmp_path, capsys):
    from cutfem.studies import conditioning
    from cutfem.studies.reproduce import main as reproduce

    afile = tmp_path / "afile"
    afile.write_text("")
    assert conditioning.main(["--tiny", "--out", str(afile)]) == 2
    assert reproduce(["--tiny", "--out", str(afile)]) == 2
    assert capsys.readouterr().err.count("--out: '" + str(afile) + "' is not a folder") == 2


def test_plot_without_errors_writes_nothing_and_says_so(tmp_path, capsys):
    import pyvista as pv

    from cutfem.geometry.surface_meshes import sphere_mesh
    from cutfem.geometry.surface import write_surface

    # a mesh file has no exact mean curvature: no error to plot (before: an empty figure, exit 0)
    path = tmp_path / "ball.obj"
    write_surface(sphere_mesh(2), path)
    plot, vtk = tmp_path / "conv.png", tmp_path / "vtk"
    assert main(["run", "mean-curvature-meshed", "--surface", str(path), "--plot", str(plot), "--vtk", str(vtk),
                 "--json", str(tmp_path / "r.json")]) == 0
    err = capsys.readouterr().err
    assert ("--plot: nothing written: the records of mean-curvature-meshed carry no errors (no exact solution "
            "for this input)") in err
    assert not plot.exists()
    # the VTK file holds the solution of the run: H_h . n = 2 on the unit sphere, to the accuracy of level 2
    saved = pv.read(vtk / "mean-curvature-meshed_n1_surface.vtp")
    assert saved.n_points == 162 and saved.point_data["H_h"].dtype == np.float64
    np.testing.assert_allclose(saved.point_data["mean_curvature"],
                               np.einsum("ij,ij->i", saved.point_data["H_h"], saved.points / np.linalg.norm(saved.points, axis=1)[:, None]),
                               rtol=0, atol=0.02)
    assert np.abs(saved.point_data["mean_curvature"] - 2.0).max() < 0.1
