"""The cutfem command and the problem registry, as a user would use them."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import cutfem
from cutfem.cli import main
from cutfem.registry import Param, ProblemError, available_problems, register

ROOT = Path(__file__).resolve().parents[1]


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
    assert files == ["mean-curvature-meshed_n16_surface.vtp", "mean-curvature-meshed_n8_surface.vtp"]
    import pyvista as pv

    poly = pv.read(vtk / files[0])
    assert poly.point_data["H_h"].shape == (poly.n_points, 3)
    assert png.stat().st_size > 5000


@pytest.mark.parametrize("argv,pattern", [
    (["run", "nope"], "unknown problem 'nope'; available:"),
    (["run", "mean-curvature-cut", "--tau-f", "-1"], "--tau-f: -1.0 must be a finite number >= 0"),
    (["run", "mean-curvature-cut", "--tau-f", "abc"], "cannot read 'abc' as float"),
    (["run", "mean-curvature-cut", "--bogus", "3"], "unknown argument.*allowed: --levels"),
    (["run", "mean-curvature-cut", "--surface", "sphere", "--radius", "3", "--box", "-1,-1,-1,1,1,1", "--levels", "0.25"], "surface reaches or leaves the box"),
    (["run", "mean-curvature-cut", "--surface", "sphere", "--radius", "0.01", "--box", "-1,-1,-1,1,1,1", "--levels", "0.25"], "too coarse to resolve the surface"),
    (["run", "mean-curvature-cut", "--surface", "sphere", "--radius", "0.01", "--box", "0.3,0.3,0.3,1,1,1", "--levels", "0.1"], "does not cut the background mesh"),
    (["run", "mean-curvature-meshed", "--surface", "missing.stl"], "neither torus, sphere nor an existing mesh file"),
    (["run", "mean-curvature-cut", "--levels", "0.1", "--tau-f", "0", "--solver", "direct"], "singular"),
])
def test_bad_input_is_one_line_and_exit_2(argv, pattern, capsys):
    assert main(argv + ["--quiet"] if argv[0] == "run" and len(argv) > 2 else argv) == 2
    err = capsys.readouterr().err
    assert re.search(pattern, err), err
    assert "Traceback" not in err


def test_open_surface_file_is_reported(tmp_path, capsys):
    from cutfem.surface import sphere_mesh

    m = sphere_mesh(1)
    tris = m.triangles[1:]  # drop one triangle: the surface is open
    import meshio

    path = tmp_path / "open.stl"
    meshio.write(path, meshio.Mesh(m.points, [("triangle", tris)]))
    assert main(["run", "mean-curvature-meshed", "--surface", str(path), "--quiet"]) == 2
    assert "open" in capsys.readouterr().err


def test_closed_surface_file_runs(tmp_path, capsys):
    from cutfem.surface import sphere_mesh, write_surface

    path = tmp_path / "ball.obj"
    write_surface(sphere_mesh(3, radius=1.5), path)
    assert main(["run", "mean-curvature-meshed", "--surface", str(path), "--json", "-"]) == 0
    rec = json.loads(capsys.readouterr().out)["records"][0]
    assert abs(rec["area"] - 4 * np.pi * 1.5**2) < 0.2
    assert np.max(np.abs(rec["integral_H"])) < 1e-9


def test_console_script_is_installed():
    out = subprocess.run([sys.executable, "-m", "cutfem.cli", "list"], capture_output=True, text=True, check=True).stdout
    assert "mean-curvature-cut" in out


def test_register_function_problem_and_run():
    @register("test-quadratic", levels=[0.5, 0.25], level_name="step", params=[Param("c", float, 2.0, "constant", minimum=0)])
    def quad(step, c):
        return {"h": step, "dofs": 1, "toy_error": c * step**2}

    res = cutfem.run("test-quadratic", c=3.0)
    assert res.rates["toy_error"] == pytest.approx([2.0])
    assert res.records[0]["toy_error"] == pytest.approx(0.75)
    assert "test-quadratic" in available_problems()
    with pytest.raises(ProblemError):
        cutfem.run("test-quadratic", c=-1)


def test_entry_point_plugins_are_loaded(monkeypatch, tmp_path):
    import importlib.metadata as md

    import cutfem.registry as reg

    (tmp_path / "my_plugin.py").write_text(
        "from cutfem import register\n"
        "@register('plugin-problem', levels=[1.0])\n"
        "def p(level):\n    return {'h': level}\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    ep = md.EntryPoint(name="plugin", value="my_plugin", group="cutfem.problems")
    monkeypatch.setattr(md, "entry_points", lambda group=None: [ep] if group == "cutfem.problems" else [])
    monkeypatch.setattr(reg, "_LOADED", False)
    assert "plugin-problem" in available_problems()


def test_readme_examples_run():
    """Every python block of the README runs (the worked Helmholtz example reaches rate ~2)."""
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert len(blocks) >= 2
    ns = {}
    for block in blocks:
        exec(compile(block, "README.md", "exec"), ns)
    result = ns["result"]
    assert result.rates["l2_error"][-1] > 1.8


def test_readme_commands_match_ci():
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    assert 'pip install -e ".[test]"' in readme and 'pip install -e ".[test]"' in ci
    assert "python -m pytest -q" in readme and "python -m pytest -q" in ci
    assert "cutfem reproduce" in readme
