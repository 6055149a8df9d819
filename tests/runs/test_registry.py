"""The problem registry: registering a problem, its parameters and their checks, the built-in
problems and the plug-ins, the levels checked before anything is solved."""

import subprocess
import sys

import numpy as np
import pytest

import cutfem
from cutfem.runs.registry import Param, ProblemError, available_problems, register


def _fresh_python(code: str) -> str:
    """The standard output of ``code`` run by a fresh interpreter (a process with nothing loaded)."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout


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

    import cutfem.runs.registry as reg

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


def test_problems_load_once_for_threads_that_ask_at_once():
    """Two threads' first look at the registry, at the same moment in a fresh interpreter, both see
    the built-in problems (the second used to find the registry empty while the first imported)."""
    import subprocess
    import sys

    code = (
        "import threading, cutfem\n"
        "barrier, seen = threading.Barrier(4), []\n"
        "def look():\n"
        "    barrier.wait()\n"
        "    seen.append('mean-curvature-cut' in cutfem.available_problems())\n"
        "threads = [threading.Thread(target=look) for _ in range(4)]\n"
        "[t.start() for t in threads]\n"
        "[t.join() for t in threads]\n"
        "print(seen)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[True, True, True, True]"


@pytest.mark.parametrize("value", [0, float("nan"), -0.1, float("inf")])
def test_bad_spacing_names_the_parameter_in_python(value):
    with pytest.raises(ProblemError, match=r"^levels: spacing .* is not a positive finite number"):
        cutfem.run("mean-curvature-cut", levels=[0.2, value])
    with pytest.raises(ProblemError, match=r"^levels: n .* is not a positive integer"):
        cutfem.run("mean-curvature-meshed", levels=[value])


@pytest.mark.parametrize("value,expected", [(2, 2), (2.0, 2), ("3", 3), (np.int64(4), 4)])
def test_int_parameter_reads_integral_values(value, expected):
    v = Param("n", int, 1).convert(value)
    assert v == expected and type(v) is int


@pytest.mark.parametrize("param,value", [
    (Param("n", int, 1), 2.5),
    (Param("n", int, 1), True),
    (Param("n", int, 1), "2.5"),
    (Param("x", float, 1.0), False),
    (Param("x", float, 1.0), float("inf")),
    (Param("x", float, 1.0), "nan"),
    (Param("theta", float, 1.0, choices=(1.0, 0.5)), 0.0),
    (Param("kind", str, "a", choices=("a", "b")), "a.b"),
])
def test_parameter_refuses_values_it_cannot_take_as_given(param, value):
    with pytest.raises(ProblemError, match=param.flag):
        param.convert(value)


def test_numeric_choices_compare_by_value_and_files_when_allowed(tmp_path):
    assert Param("theta", float, 1.0, choices=(1.0, 0.5)).convert("0.5") == 0.5
    mesh = tmp_path / "m.stl"
    mesh.write_text("solid\nendsolid\n")
    surface = Param("surface", str, "torus", choices=("torus", "sphere"), files=True)
    assert surface.convert(str(mesh)) == str(mesh) and surface.convert("sphere") == "sphere"
    with pytest.raises(ProblemError, match="neither torus, sphere nor an existing file"):
        surface.convert(str(tmp_path / "missing.stl"))
    with pytest.raises(ProblemError, match="is not one of torus, sphere"):
        Param("surface", str, "torus", choices=("torus", "sphere")).convert(str(mesh))


def test_builtin_problem_names_cannot_be_taken():
    for name in ("mean-curvature-cut", "heat-surface-cut"):  # a class and a function problem
        with pytest.raises(ValueError, match=f"'{name}' is the name of a built-in problem"):
            @register(name, levels=[1.0])
            def mine(level):
                return {"h": level}
    assert "stabilized mean curvature" in available_problems()["mean-curvature-cut"].summary


def test_a_problem_registered_before_the_builtins_load_stays():
    code = (
        "from cutfem import register, available_problems\n"
        "import cutfem.runs.registry as reg\n"
        "assert not reg._LOADED\n"
        "try:\n"
        "    register('poisson-cut', levels=[1.0])(lambda level: {'h': level})\n"
        "except ValueError as exc:\n"
        "    print('refused:', exc)\n"
        "register('early-problem', levels=[1.0], summary='mine')(lambda level: {'h': level})\n"
        "problems = available_problems()\n"
        "print(problems['early-problem'].summary, 'poisson-cut' in problems, problems['poisson-cut'].summary[:14])\n"
        "register('early-problem', levels=[1.0], summary='again')(lambda level: {'h': level})\n"
        "print(available_problems()['early-problem'].summary)\n"
    )
    assert _fresh_python(code).splitlines() == [
        "refused: 'poisson-cut' is the name of a built-in problem; register yours under another name",
        "mine True fictitious-dom",
        "again",  # a cell run twice replaces the earlier one
    ]


def test_records_name_only_the_parameters_that_shape_the_run():
    sphere = cutfem.run("mean-curvature-cut", levels=[0.4], surface="sphere", radius=0.9)
    assert sphere.parameters["radius"] == 0.9 and not {"R", "r", "axes"} & set(sphere.parameters)
    torus = cutfem.run("mean-curvature-meshed", levels=[8])
    assert {"R", "r", "family"} <= set(torus.parameters) and not {"radius", "seed"} & set(torus.parameters)
    flipped = cutfem.run("mean-curvature-meshed", levels=[8], family="flipped", seed=2)
    assert flipped.parameters["seed"] == 2  # the seed shapes the random families only
