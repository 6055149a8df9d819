"""The performance benchmark at a tiny size: its JSON fields, and the iterative solve against the direct one."""

import json

import numpy as np
import pytest

from cutfem.cut import cut_mesh
from cutfem.errors import l2_error
from cutfem.levelset import Torus
from cutfem.mesh import structured_box
from cutfem.solve import solve
from cutfem.spaces import CutP1Space, SurfaceP1Space
from cutfem.studies import performance
from surface_matrices import edge_matrix, face_matrix, mass_matrix, stiffness_matrix


def test_levels_record_stages_sizes_and_errors():
    rec = performance.cut_level(0.2)
    assert set(rec["time"]) == {"background", "cut", "topology", "mass", "rhs", "face_penalty", "system", "solve", "errors"}
    assert rec["background_nodes"] == 17 * 17 * 7
    assert rec["active_tets"] > 0 and rec["interior_faces"] > rec["active_tets"] and rec["dofs"] > 0
    assert 0 < rec["l2_error"] < 2.0
    assert rec["total"] == pytest.approx(sum(rec["time"].values()))
    m = performance.meshed_level(16, "flipped")
    assert m["dofs"] == 16 * 8 and m["triangles"] == 2 * 16 * 8
    assert set(m["time"]) >= {"mesh", "mass", "rhs", "edge_penalty", "solve", "errors"}


def test_run_tiny_writes_json_and_figure(tmp_path):
    summary = performance.run(tmp_path, "tiny", progress=lambda msg: None)
    data = json.loads((tmp_path / "performance.json").read_text())
    kinds = {r["kind"] for r in data["levels"]}
    assert kinds == {"cut", "meshed-flipped", "meshed-perturbed"}
    for r in data["levels"]:
        assert r["peak_memory_gib"] > 0.01 and r["total"] > 0 and r["dofs"] > 0
        assert r["cpu_user"] > 0 and r["cpu_system"] >= 0 and r["page_faults"] >= 0
        assert set(r["allocator"]) >= {"malloc", "numpy_hugepage", "thp_defrag"}
    assert (tmp_path / "performance_scaling.png").stat().st_size > 10_000
    assert summary["levels"] == data["levels"]
    assert data["repeat"] == 1 and all(r["totals"] == [r["total"]] for r in data["levels"])
    assert performance.fitted_exponent([1, 10, 100], [2, 20, 200]) == pytest.approx(1.0)


@pytest.mark.parametrize("spacing", [0.05])
def test_iterative_and_direct_solves_agree(spacing):
    """Multigrid-preconditioned CG (tolerance 1e-8) against the sparse direct solve: the L2 errors
    agree to far more than 3 significant digits and the solutions to the tolerance."""
    torus = Torus()
    space = CutP1Space(cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=spacing), torus))
    K = mass_matrix(space) + 0.1 * face_matrix(space)
    B = stiffness_matrix(space) @ space.dof_points
    Hd, info_d = solve(K, B, method="direct")
    Hi, info_i = solve(K, B, method="cg-mg", space=space, tol=1e-8)
    assert info_d.method == "direct" and info_i.method.startswith("cg") and info_i.iterations > 0
    assert np.linalg.norm(Hi - Hd) <= 1e-6 * np.linalg.norm(Hd)
    ed = l2_error(space, Hd, torus.exact_mean_curvature_vector)
    ei = l2_error(space, Hi, torus.exact_mean_curvature_vector)
    assert abs(ed - ei) <= 1e-6 * ed


@pytest.mark.parametrize("family", ["flipped", "perturbed"])
def test_meshed_multigrid_and_direct_errors_agree(family):
    """The meshed torus with the default tolerance (1e-8): CG with the grid multigrid and SuperLU
    give L2 errors that agree to at least 5 significant digits (3 are asked for)."""
    from cutfem.surface import torus_mesh

    V = SurfaceP1Space(torus_mesh(128, family, seed=1))
    K = mass_matrix(V) + 0.1 * edge_matrix(V)
    B = stiffness_matrix(V) @ V.dof_points
    Hd, _ = solve(K, B, method="direct")
    Hi, info = solve(K, B, method="cg-mg", space=V)
    assert info.method == "cg-mg" and 0 < info.iterations <= 30 and info.residual <= 1e-6
    exact = Torus().exact_mean_curvature_vector
    ed, ei = l2_error(V, Hd, exact), l2_error(V, Hi, exact)
    assert abs(ed - ei) <= 1e-5 * ed
