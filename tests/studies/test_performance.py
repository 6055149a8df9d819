"""The performance benchmark at a tiny size: its JSON fields, and the iterative solve against the direct one."""

import json

import numpy as np
import pytest

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.norms import l2_error
from cutfem.geometry.shapes import Torus
from cutfem.geometry.box import structured_box
from cutfem.solvers.solve import solve
from cutfem.fem.spaces import CutSpace, SurfaceP1Space
from cutfem.studies import performance, performance_levels
from surface_matrices import edge_matrix, face_matrix, mass_matrix, stiffness_matrix


@pytest.mark.slow
def test_run_tiny_writes_json_and_figure(tmp_path, monkeypatch):
    """Tiny run with the bulk table and --peers where ngsxfem is reported missing: a note, no failure."""
    monkeypatch.setattr(performance, "_peer_missing", lambda: "ngsolve/xfem are not importable (test)")
    summary = performance.run(tmp_path, "tiny", progress=lambda msg: None, peers=True, bulk=True)
    data = json.loads((tmp_path / "performance.json").read_text())
    kinds = {r["kind"] for r in data["levels"]}
    assert kinds == {"cut", "meshed-flipped", "meshed-perturbed"}
    for r in data["levels"]:
        assert r["peak_memory_gib"] > 0.01 and r["total"] > 0 and r["dofs"] > 0
        assert r["cpu_user"] > 0 and r["cpu_system"] >= 0 and r["page_faults"] >= 0
        assert set(r["allocator"]) >= {"malloc", "numpy_hugepage", "thp_defrag"}
        # run again in its process: the same stages and iterations, the start-up the difference of the totals
        assert set(r["warm"]["time"]) == set(r["time"]) and r["warm"]["iterations"] == r["iterations"]
        # six-digit JSON (studies.common.save_json): sums and differences of rounded times
        assert r["warm"]["total"] == pytest.approx(sum(r["warm"]["time"].values()), rel=2e-5)
        assert r["start_up"] == pytest.approx(r["total"] - r["warm"]["total"], abs=2e-5 * r["total"])
        if r["kind"] == "cut":  # a bound for every stage, with its method, and measured / bound
            assert set(r["bounds"]) == set(r["time"])
            assert r["nnz"]["K"] > 7 * r["dofs"]  # each node couples to its neighbours through the face penalty
            for stage, b in r["bounds"].items():
                assert b["bound_method"] and b["measured"] == r["warm"]["time"][stage] and b["measured_fresh"] == r["time"][stage]
                assert (b["ratio"] is None) == (stage == "background")
    assert data["bandwidth"]["bandwidth"] > 1e8
    assert data["peers"] == {"skipped": "ngsolve/xfem are not importable (test)"}
    assert [r["level"] for r in data["bulk"]] == [0.2]
    for r in data["bulk"]:
        assert r["dofs"] > 1000 and r["peak_memory_gib"] > 0.01 and set(r["time"]) == {"geometry", "assembly", "solve", "errors"}
        assert r["seconds_per_million"] == pytest.approx(r["wall"] / (r["dofs"] / 1e6), rel=2e-5)  # six-digit JSON (studies.common.save_json)
    assert data["exponents"]["cut"] == {}  # two cut levels: too few to fit
    assert "cut from 0.025" not in data["exponents"]  # none at 0.025 or finer at the tiny size
    assert set(data["stage_targets"]) == {"cut", "topology", "matrix", "rhs", "solve", "errors"}
    refs = data["compiled_references"]  # at the tiny size, spacing 0.1, in a fresh process
    assert [r["spacing"] for r in refs] == [0.1] * 8 and all(r["cutfem"] > 0 and r["reference_time"] > 0 for r in refs)
    # the commands of the targets, end to end in fresh processes: the tiny sizes, without a target
    commands = data["commands"]
    assert [c["command"] for c in commands] == ["cutfem run mean-curvature-cut --spacing 0.1"] + [
        f"cutfem run mean-curvature-meshed --levels 32 --family {f}" for f in ("structured", "flipped", "perturbed", "perturbed-flipped")]
    cut_tiny = [r for r in data["levels"] if r["kind"] == "cut" and r["level"] == 0.1][0]
    assert commands[0]["dofs"] == cut_tiny["dofs"]  # the same level as the staged run
    for c in commands:
        assert len(c["walls"]) == 1 and c["median"] == c["min"] == c["max"] == c["walls"][0]
        assert 0.2 < c["median"] < 60 and c["peak_memory_gib"] > 0.05 and c["target"] is None and c["met"] is None
    assert [t for _, t in performance_levels.command_targets("quick")] == [2.0, 1.0, 1.0, 1.0, 1.0]
    assert performance_levels.command_targets("full")[-1] == (["run", "mean-curvature-cut", "--spacing", "0.003125"], 40.0)
    for name in ("performance_scaling", "performance_bounds"):
        assert (tmp_path / f"{name}.png").stat().st_size > 10_000
    assert summary["levels"] == data["levels"]
    assert data["repeat"] == 1 and all(r["totals"] == [r["total"]] for r in data["levels"])
    assert performance.fitted_exponent([1, 10, 100], [2, 20, 200]) == pytest.approx(1.0)


def test_scaling_exponents_over_the_three_finest_levels():
    # time ~ tets^1.5 and memory ~ tets on the three finest; the coarsest level lies off both laws
    recs = [{"level": s, "active_tets": t, "total": t**1.5 if t > 10 else 1.0, "cpu_user": 2 * t, "peak_memory_gib": 3 * t if t > 10 else 5.0,
             "time": {"solve": t**1.2, "cut": 0.0}} for s, t in ((0.4, 10), (0.2, 100), (0.1, 1000), (0.05, 10000))]
    e = performance.scaling_exponents(recs, stages=("solve", "cut"))
    assert e["levels"] == [0.2, 0.1, 0.05]
    assert e["time"] == pytest.approx(1.5) and e["memory"] == pytest.approx(1.0) and e["user_time"] == pytest.approx(1.0)
    assert e["stages"] == {"solve": pytest.approx(1.2)}  # a stage timed at 0 has no exponent
    assert performance.scaling_exponents(recs[:2]) == {}
    for r in recs:
        r["wall"] = r.pop("total")
    assert performance.scaling_exponents(recs, time_key="wall")["time"] == pytest.approx(1.5)


def _fake_runner(peak_of_tets, ran, fail_at=None):
    """A cut level with 1000 (0.1 / s)^2 active tets and the given peak; records the spacings run."""
    def runner(s):
        ran.append(s)
        if fail_at is not None and s <= fail_at:
            return {"level": s, "failed": "out of memory"}
        t = 1000 * (0.1 / s) ** 2
        return {"level": s, "active_tets": t, "peak_memory_gib": peak_of_tets(t), "total": 1.0}
    return runner


def test_limit_stops_before_the_level_predicted_to_exceed():
    ran = []
    # peak = 1e-3 GiB a tet: 1, 4, 16, 64 GiB at 0.1, 0.05, 0.025, 0.0125; with 20 GiB, 0.0125 is predicted at 64
    lim = performance.limit_search(_fake_runner(lambda t: 1e-3 * t, ran), 20.0)
    assert ran == [0.1, 0.05, 0.025]
    assert lim["largest"]["level"] == 0.025 and lim["largest"]["peak_memory_gib"] == pytest.approx(16.0)
    assert lim["next"]["spacing"] == 0.0125
    assert lim["next"]["peak_memory_gib"] == pytest.approx(64.0) and lim["next"]["active_tets"] == pytest.approx(64000)
    assert lim["next"]["memory_exponent"] == pytest.approx(1.0) and lim["next"]["tets_exponent"] == pytest.approx(-2.0)
    assert "0.0125 predicted" in lim["stopped"]
    # a tiny limit: the first level runs, the second is predicted (assumed factor 4) above it
    ran.clear()
    lim = performance.limit_search(_fake_runner(lambda t: 0.5 + 1e-4 * t, ran), 1.0)
    assert ran == [0.1] and lim["largest"]["level"] == 0.1
    assert lim["next"]["peak_memory_gib"] == pytest.approx(4 * 0.6)
    # a fixed start-up memory makes the fitted exponent < 1 (0.45 over 0.1-0.025); the prediction uses 1:
    # 2.1 x 4 = 8.4 GiB > 5 at 0.0125 (true 6.9 GiB), where the fit alone would predict 3.9 GiB and run it
    ran.clear()
    lim = performance.limit_search(_fake_runner(lambda t: 0.5 + 1e-4 * t, ran), 5.0)
    assert ran == [0.1, 0.05, 0.025] and lim["next"]["memory_exponent"] < 0.5
    assert lim["next"]["memory_exponent_used"] == 1.0 and lim["next"]["peak_memory_gib"] == pytest.approx(4 * 2.1)
    # memory available now caps the limit: 90 % of 5 GiB < 16 GiB predicted at 0.025
    ran.clear()
    lim = performance.limit_search(_fake_runner(lambda t: 1e-3 * t, ran), 20.0, available_gib=lambda: 5.0)
    assert ran == [0.1, 0.05] and "available" in lim["stopped"]


def test_limit_records_a_failed_or_oversized_level():
    ran = []
    lim = performance.limit_search(_fake_runner(lambda t: 1e-3 * t, ran, fail_at=0.025), 20.0)
    assert ran == [0.1, 0.05, 0.025] and lim["largest"]["level"] == 0.05 and "failed" in lim["stopped"]
    # a level over the limit although predicted below it (memory grows faster than the fit): not the largest
    ran.clear()
    lim = performance.limit_search(_fake_runner(lambda t: 1e-3 * t if t < 5000 else 30.0, ran), 20.0)
    assert ran == [0.1, 0.05, 0.025] and lim["largest"]["level"] == 0.05 and "30.00 GiB > 20 GiB" in lim["stopped"]
    ran.clear()
    lim = performance.limit_search(_fake_runner(lambda t: 5.0, ran), 1.0)
    assert ran == [0.1] and lim["largest"] is None and lim["next"] is None
    with pytest.raises(ValueError, match="memory-gib"):
        performance.limit_search(_fake_runner(lambda t: 1.0, ran), 0)


def test_command_line_has_one_parser_and_checks_the_memory_limit(capsys):
    """The benchmark's own options and the usual study options are one parser: one usage, one help."""
    from cutfem.studies import peers

    for main, own in ((performance.main, "--memory-gib"), (peers.main, "--problem")):
        with pytest.raises(SystemExit) as exc:
            main(["--help"])
        text = capsys.readouterr().out
        assert exc.value.code == 0 and text.count("usage:") == 1 and own in text and "--out" in text and "--full" in text
    for bad in ("-1", "0", "nan", "inf", "lots"):
        with pytest.raises(SystemExit) as exc:
            performance.main(["--memory-gib", bad])
        assert exc.value.code == 2 and "positive number of GiB" in capsys.readouterr().err


@pytest.mark.parametrize("spacing", [0.05])
def test_iterative_and_direct_solves_agree(spacing):
    """Multigrid-preconditioned CG (tolerance 1e-8) against the sparse direct solve: the L2 errors
    agree to far more than 3 significant digits and the solutions to the tolerance."""
    torus = Torus()
    space = CutSpace(cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=spacing), torus))
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
    from cutfem.geometry.surface_meshes import torus_mesh

    V = SurfaceP1Space(torus_mesh(128, family, seed=1))
    K = mass_matrix(V) + 0.1 * edge_matrix(V)
    B = stiffness_matrix(V) @ V.dof_points
    Hd, _ = solve(K, B, method="direct")
    Hi, info = solve(K, B, method="cg-mg", space=V)
    assert info.method == "cg-mg" and 0 < info.iterations <= 30 and info.residual <= 1e-6
    exact = Torus().exact_mean_curvature_vector
    ed, ei = l2_error(V, Hd, exact), l2_error(V, Hi, exact)
    assert abs(ed - ei) <= 1e-5 * ed
