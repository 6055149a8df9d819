"""The flat face: ``import cutfem as cf`` gives the public names, lazily, and nothing else changes."""

import importlib
import pkgutil
import subprocess
import sys

import pytest

import cutfem

# the defining module of each public name, written out here (not read from cutfem._NAMES)
EXPECTED = {
    "cutfem.geometry.box": "structured_box",
    "cutfem.geometry.mesh": "read_mesh write_mesh",
    "cutfem.geometry.surface": "read_surface write_surface",
    "cutfem.geometry.surface_meshes": "sphere_mesh torus_mesh",
    "cutfem.geometry.shapes": "Sphere Torus Ellipsoid Plane",
    "cutfem.geometry.csg": "intersection union difference complement Domain",
    "cutfem.geometry.levelset": "FunctionLevelSet",
    "cutfem.geometry.signed_distance": "SignedDistance",
    "cutfem.geometry.cut": "cut_mesh CutMesh",
    "cutfem.geometry.csg_cut": "CsgCut",
    "cutfem.geometry.markers": "NEG POS CUT",
    "cutfem.fem.spaces": "CutSpace SurfaceP1Space VectorSpace RealSpace ProductSpace",
    "cutfem.fem.forms": "bilinear_form linear_form assemble",
    "cutfem.fem.pointwise": "dot inner jump avg ZERO",
    "cutfem.fem.terms": "apply_dirichlet mass stiffness tangential_stiffness load position_load basis_integrals nitsche "
                        "interface_nitsche face_jump_penalty edge_jump_penalty normal_gradient_penalty",
    "cutfem.fem.elasticity": "elasticity elasticity_nitsche",
    "cutfem.fem.coupling": "divergence mean_constraint",
    "cutfem.fem.norms": "l2_error h1_error l2_h1_errors rates fitted_rate",
    "cutfem.runs.registry": "register Param Problem available_problems get_problem",
    "cutfem.runs.runner": "run",
    "cutfem.solvers.solve": "solve",
    "cutfem.solvers.diagnose": "SolverError",
    "cutfem.solvers.direct": "DirectSolver",
    "cutfem.solvers.krylov": "CGSolver",
    "cutfem.solvers.multigrid": "GeometricMultigrid",
    "cutfem.fem.exact": "Exact",
    "cutfem.fem.moving": "ActiveDomain strip_width transfer",
    "cutfem.distributed.launch": "launched_rank",
}


def test_all_lists_exactly_the_expected_names():
    expected = {name for names in EXPECTED.values() for name in names.split()} | {"__version__"}
    assert set(cutfem.__all__) == expected
    assert len(cutfem.__all__) == len(expected)  # no name twice


@pytest.mark.parametrize("module, name", [(m, n) for m, names in EXPECTED.items() for n in names.split()])
def test_each_name_is_the_object_of_its_module(module, name):
    assert getattr(cutfem, name) is getattr(importlib.import_module(module), name)


def test_solve_is_the_function_after_the_solver_modules_are_imported():
    import cutfem.solvers.solve  # noqa: F401  (binds cutfem.solvers, not cutfem.solve)

    assert cutfem.solve is sys.modules["cutfem.solvers.solve"].solve and callable(cutfem.solve)


def test_no_public_name_is_a_submodule():
    submodules = {info.name for info in pkgutil.iter_modules(cutfem.__path__)}
    assert submodules == {"distributed", "fem", "geometry", "jit", "memory", "runs", "solvers"}
    assert not submodules & set(cutfem.__all__)


def test_dir_lists_the_public_names():
    assert set(cutfem.__all__) <= set(dir(cutfem))


def test_unknown_name_raises_attribute_error_naming_it_and_the_close_match():
    with pytest.raises(AttributeError, match=r"no attribute 'stifness'; did you mean cutfem\.stiffness\?"):
        cutfem.stifness
    with pytest.raises(AttributeError, match=r"no attribute 'qwertyuiop'$"):
        cutfem.qwertyuiop
    assert not hasattr(cutfem, "not_a_name")


def test_submodules_still_import_by_from():
    from cutfem import memory
    from cutfem.runs import registry

    assert registry.register is cutfem.register and callable(memory.configure)


def _fresh(code):
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_import_is_light_and_changes_nothing_process_wide():
    out = _fresh(
        "import os, sys\n"
        "env = dict(os.environ)\n"
        "import cutfem\n"
        "heavy = [m for m in ('numba', 'scipy', 'scipy.sparse.linalg', 'matplotlib', 'cutfem.jit', 'cutfem.runs.registry',"
        " 'cutfem.runs.runner')"
        " if m in sys.modules]\n"
        "print(heavy, dict(os.environ) == env)\n"
    )
    assert out.strip() == "[] True"


def test_star_import_gives_every_public_name():
    out = _fresh(
        "from cutfem import *\n"
        "import cutfem\n"
        "missing = [n for n in cutfem.__all__ if n not in globals()]\n"
        "print(missing, solve is cutfem.solve, NEG is cutfem.NEG)\n"
    )
    assert out.strip() == "[] True True"
