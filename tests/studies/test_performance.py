"""The performance benchmark at a tiny size: its JSON fields, and the iterative solve against the direct one."""

import json

import numpy as np
import pytest

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.norms import l2_error
from cutfem.geometry.shapes import Torus
from cutfem.geometry.box import structured_box
from cutfem.solvers.solve import solve
from cutfem.fem.spaces import CutP1Space, SurfaceP1Space
from cutfem.studies import performance
from surface_matrices import edge_matrix, face_matrix, mass_matrix, stiffness_matrix


def test_levels_record_stages_sizes_and_errors():
    rec = performance.cut_level(0.2)
    assert set(rec["time"]) == {"background", "cut", "topology", "matrix", "rhs", "solve", "errors"}
    assert rec["background_nodes"] == 17 * 17 * 7
    assert rec["active_tets"] > 0 and rec["interior_faces"] > rec["active_tets"] and rec["dofs"] > 0
    assert 0 < rec["l2_error"] < 2.0
    assert rec["total"] == pytest.approx(sum(rec["time"].values()))
    m = performance.meshed_level(16, "flipped")
    assert m["dofs"] == 16 * 8 and m["triangles"] == 2 * 16 * 8
    assert set(m["time"]) == {"mesh", "matrix", "rhs", "solve", "errors"}


def test_stage_timer_keeps_cpu_and_faults_per_stage():
    """Per stage: the wall time, and user and system CPU time and minor page faults from getrusage.
    A stage that writes 64 MiB of a fresh anonymous mapping faults at least once per 2 MiB (once
    per 4 KiB page without transparent huge pages); a stage that only sleeps spends no CPU time."""
    import mmap
    import time

    t = performance.StageTimer()
    region = mmap.mmap(-1, 64 * 2**20)  # fresh pages, not the allocator's reused heap
    with t("touch"):
        np.frombuffer(region, dtype=np.float64)[:] = 1.0
    with t("sleep"):
        time.sleep(0.05)
    with t("touch"):
        np.frombuffer(region, dtype=np.float64)[::512] += 1.0  # pages already there: no new faults needed
    assert set(t) == set(t.cpu) == {"touch", "sleep"}
    assert t["sleep"] >= 0.05 and t.cpu["sleep"]["user"] + t.cpu["sleep"]["system"] < 0.04
    assert t.cpu["touch"]["faults"] >= 64 // 2
    assert t.cpu["touch"]["user"] + t.cpu["touch"]["system"] <= 2 * t["touch"] + 0.02  # two cores at most
    assert np.frombuffer(region, dtype=np.float64)[512] == 2.0
    rec = performance.cut_level(0.2)
    assert set(rec["stage_cpu"]) == set(rec["time"])


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
    assert [t for _, t in performance.command_targets("quick")] == [2.0, 1.0, 1.0, 1.0, 1.0]
    assert performance.command_targets("full")[-1] == (["run", "mean-curvature-cut", "--spacing", "0.003125"], 40.0)
    for name in ("performance_scaling", "performance_bounds"):
        assert (tmp_path / f"{name}.png").stat().st_size > 10_000
    assert summary["levels"] == data["levels"]
    assert data["repeat"] == 1 and all(r["totals"] == [r["total"]] for r in data["levels"])
    assert performance.fitted_exponent([1, 10, 100], [2, 20, 200]) == pytest.approx(1.0)


def test_peak_memory_is_the_level_process_own():
    """A parent that once held 0.4 GiB: the child's ru_maxrss would start there (Linux), its VmHWM does not."""
    import resource

    a = np.ones(50_000_000)
    a[1::512] = 2.0
    del a
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20 > 0.37
    rec = performance._in_subprocess("meshed-flipped", 16)
    assert 0.02 < rec["peak_memory_gib"] < 0.3
    assert "warm" in rec and "warm" not in performance._in_subprocess("meshed-flipped", 16, warm=False)  # --limit: once


def test_the_second_run_of_a_level_reuses_the_memory_of_the_first():
    """The objects of a level refer to each other, so the level process collects them before its
    second run: that run then takes its memory from the heap the first one freed, instead of
    touching fresh pages beside the first run's (about 1550 faults at spacing 0.05 without the
    collection, against about 20 thousand for the first run and a handful with it)."""
    rec = performance._in_subprocess("cut", 0.05)
    assert rec["page_faults"] > 5000
    assert 0 <= rec["warm"]["page_faults"] < rec["page_faults"] / 20


def _fabricated_level(**changes):
    rec = {"level": 0.05, "dofs": 500, "active_tets": 1000, "surface_triangles": 1200, "interior_faces": 2000,
           "iterations": 10, "nnz": {"K": 8000},
           "time": {"background": 1e-5, "cut": 1.088e-4, "topology": 1.6e-4, "matrix": 4.184e-4, "rhs": 6.8e-5,
                    "solve": 3.12e-3, "errors": 5.76e-4}}
    rec.update(changes)
    return rec


def test_stage_targets_by_hand():
    """Each stage's verdict from the finest level's own time / traffic bound and, where the stage
    has compiled references, the largest cutfem-on-one-thread / reference time: the cut 0.5, the
    topology 0.25, the matrix 3.0 and the right-hand sides 2.5 by their whole-stage rows, the solve
    1.5 by the worst of its three kernels; the coarser level's ratios are not used; the errors
    have no reference, and the share of their own (second-run) time in the exact field."""
    coarse = _fabricated_level(level=0.1)
    fine = _fabricated_level(level=0.05, time={k: v / 10 if k == "solve" else v for k, v in coarse["time"].items()})
    fine["warm"] = {"time": {**fine["time"], "errors": 4e-4}, "exact_time": 1e-4}
    for r in (coarse, fine):
        r["bounds"] = performance.stage_bounds(r, 1e10)  # ratios 10 (the fine solve: 1)
    coarse["bounds"]["cut"]["ratio"] = 1.0  # would pass the cut if the coarse level were used

    def row(name, one_thread, reference):
        return {"operation": name, "cutfem_one_thread": one_thread, "reference_time": reference,
                "per_thread": reference / one_thread}

    refs = [row("the cut stage (band, S_h), whole", 1.0, 2.0), row("the matrix stage, whole", 3.0, 1.0),
            row("K X, 3 columns, double", 1.0, 2.0), row("Gauss-Seidel sweep from zero, 3 columns", 1.5, 1.0),
            row("Galerkin P^T K P, first level", 1.0, 1.0), row("active-node numbering", 9.0, 1.0),
            row("the topology stage (interior faces), whole", 1.0, 4.0), row("the right-hand sides, whole", 5.0, 2.0)]
    t = performance.stage_targets([coarse, fine], refs)
    assert list(t) == ["cut", "topology", "matrix", "rhs", "solve", "errors"]
    assert all(v["level"] == 0.05 for v in t.values())
    assert t["cut"]["compiled_ratio"] == pytest.approx(0.5) and t["cut"]["traffic_ratio"] == pytest.approx(10.0)
    assert t["matrix"]["compiled_ratio"] == pytest.approx(3.0) and not t["matrix"]["within_2x"]
    assert t["solve"]["compiled_ratio"] == pytest.approx(1.5) and len(t["solve"]["references"]) == 3
    assert t["solve"]["traffic_ratio"] == pytest.approx(1.0) and t["solve"]["within_2x"]
    assert t["topology"]["compiled_ratio"] == pytest.approx(0.25) and t["topology"]["within_2x"]
    assert t["rhs"]["compiled_ratio"] == pytest.approx(2.5) and not t["rhs"]["within_2x"]
    assert t["cut"]["within_2x"] and not t["errors"]["within_2x"]
    assert t["errors"]["compiled_ratio"] is None and t["errors"]["references"] == []
    assert t["errors"]["exact_share"] == pytest.approx(0.25) and "exact_share" not in t["cut"]
    del fine["warm"]
    assert "exact_share" not in performance.stage_targets([coarse, fine], refs)["errors"]  # not recorded
    assert performance.stage_targets([], refs) == {}


def test_stage_bounds_by_hand():
    """N = 500, T = 1000, S = 1200, F = 2000, it = 10, nnz(K) = 8000 at 1e10 bytes/s; the times are
    10 x the bounds worked out here."""
    bytes_by_hand = {
        "background": 0,
        "cut": 16 * 500 + 72 * 1000 + 24 * 1200,  # 108 800
        "topology": 96 * 1000 + 32 * 2000,  # 160 000
        "matrix": 52 * 1200 + 48 * 2000 + 328 * 500 + 12 * 8000,  # 62 400 + 96 000 + 164 000 + 96 000 = 418 400
        "rhs": 56 * 1000 + 24 * 500,  # 68 000
        "solve": 10 * (24 * 8000 + 80 * 3 * 500),  # 3 120 000
        "errors": 80 * 6 * 1200,  # 576 000
    }
    rec = _fabricated_level()
    b = performance.stage_bounds(rec, 1e10)
    assert set(b) == set(bytes_by_hand)
    for stage, nbytes in bytes_by_hand.items():
        assert b[stage]["bytes"] == pytest.approx(nbytes)
        assert b[stage]["bound"] == pytest.approx(nbytes / 1e10)
        assert b[stage]["bound_method"].startswith("memory traffic / 10.00 GB/s")
    assert b["solve"]["bound"] == pytest.approx(3.12e-4)
    for stage in ("cut", "topology", "matrix", "rhs", "solve", "errors"):
        assert b[stage]["ratio"] == pytest.approx(10.0), stage
    assert b["background"]["ratio"] is None
    # a level run again in its process: its stages at half the time, compared with the same bounds
    warm = performance.stage_bounds(_fabricated_level(warm={"time": {k: v / 2 for k, v in rec["time"].items()}}), 1e10)
    for stage in ("cut", "topology", "matrix", "rhs", "solve", "errors"):
        assert warm[stage]["ratio"] == pytest.approx(5.0) and warm[stage]["ratio_fresh"] == pytest.approx(10.0), stage
        assert warm[stage]["measured"] == rec["time"][stage] / 2 and warm[stage]["measured_fresh"] == rec["time"][stage]
    # a direct solve (no iterations): K read once and the 500 x 3 solution written
    direct = performance.stage_bounds(_fabricated_level(iterations=0), 1e10)["solve"]
    assert direct["bytes"] == 12 * 8000 + 24 * 500 and "direct" in direct["bound_method"]
    with pytest.raises(ValueError, match="bandwidth"):
        performance.stage_bounds(rec, 0.0)


def test_memory_bandwidth_is_a_plausible_rate():
    bw = performance.memory_bandwidth(16, repeat=2)
    assert 1e8 < bw["copy"] < 1e12 and 1e8 < bw["triad"] < 1e12
    assert bw["bandwidth"] == max(bw["copy"], bw["triad"]) and "best of 2" in bw["method"]
    two = performance.memory_bandwidth(16, repeat=2, threads=2)
    assert two["threads"] == 2 and "2 thread(s)" in two["method"] and 1e8 < two["copy"] < 1e12


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


def test_the_topology_reference_matches_the_same_faces():
    """VTK's geometry filter, the topology stage's reference, keeps exactly the faces of the active
    tets that the interior faces leave unpaired (cut torus at spacing 0.2, as sorted node triples)."""
    import pyvista as pv

    from cutfem.geometry.cut import CUT, cut_mesh
    from cutfem.geometry.shapes import Torus
    from cutfem.geometry.markers import interior_facets
    from cutfem.geometry.box import structured_box
    from cutfem.geometry.numbering import TET_FACES

    es = cut_mesh(structured_box(*performance.BOX, spacing=0.2), Torus(1.0, 0.5)).elements(CUT)
    tets = np.asarray(es.tets)
    pairs, opposite = interior_facets(es.tets, es.n_nodes, es.kuhn_types)
    paired = np.zeros((len(tets), 4), dtype=bool)
    paired[pairs[:, 0], opposite[:, 0]] = paired[pairs[:, 1], opposite[:, 1]] = True
    tet, vertex = np.nonzero(~paired)  # face k of a tet is the one opposite to its local vertex k
    ours = np.unique(np.sort(tets[tet[:, None], TET_FACES[vertex]], axis=1), axis=0)
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: tets}, np.asarray(es.points))
    surface = grid.extract_surface(pass_pointid=True, pass_cellid=False, algorithm="geometry")
    theirs = np.unique(np.sort(surface.point_data["vtkOriginalPointIds"][surface.regular_faces], axis=1), axis=0)
    assert len(ours) == 4 * len(tets) - 2 * len(pairs) > 1000
    np.testing.assert_array_equal(ours, theirs)


def test_compiled_references_compute_what_their_kernels_compute():
    """Each kernel and its compiled reference (scipy's CSR product and sparse products, pyamg's
    Gauss-Seidel, numpy.unique, VTK's contour and geometry filters, scipy's COO to CSR,
    numpy.bincount) give the same result on the cut torus at spacing 0.2: the product, the
    numbering and the number of boundary faces exactly, the sweep, the Galerkin product, the
    surface's area, the matrix and the right-hand sides to round-off; per thread is the reference's
    time over cutfem's on one thread."""
    rows = performance.compiled_references(0.2, repeat=1)
    assert [r["operation"] for r in rows] == ["K X, 3 columns, double", "Gauss-Seidel sweep from zero, 3 columns",
                                              "Galerkin P^T K P, first level", "active-node numbering",
                                              "the cut stage (band, S_h), whole", "the matrix stage, whole",
                                              "the topology stage (interior faces), whole", "the right-hand sides, whole"]
    by = {r["operation"]: r for r in rows}
    # VTK's marching tets on the active tets give the same surface (relative difference of the areas),
    # and the element matrices summed by scipy's COO to CSR conversion give K
    assert by["the cut stage (band, S_h), whole"]["difference"] < 1e-12
    assert by["the matrix stage, whole"]["difference"] < 1e-12
    assert by["the topology stage (interior faces), whole"]["difference"] == 0.0  # VTK's boundary: 4 T - 2 F faces
    assert by["the right-hand sides, whole"]["difference"] < 1e-12
    assert by["K X, 3 columns, double"]["difference"] == 0.0
    assert by["active-node numbering"]["difference"] == 0.0
    assert by["Gauss-Seidel sweep from zero, 3 columns"]["difference"] < 1e-12
    assert by["Galerkin P^T K P, first level"]["difference"] < 1e-12
    for r in rows:
        assert r["unknowns"] > 1000 and r["cutfem"] > 0 and r["cutfem_one_thread"] > 0 and r["reference_time"] > 0
        assert r["per_thread"] == pytest.approx(r["reference_time"] / r["cutfem_one_thread"])
