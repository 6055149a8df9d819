"""What the benchmark's stages are held against (cutfem.studies.performance_bounds): the
memory-traffic bounds worked out by hand, the bandwidth, the compiled references and the
per-stage targets."""

import numpy as np
import pytest

from cutfem.studies import performance_bounds, performance_levels


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
        r["bounds"] = performance_bounds.stage_bounds(r, 1e10)  # ratios 10 (the fine solve: 1)
    coarse["bounds"]["cut"]["ratio"] = 1.0  # would pass the cut if the coarse level were used

    def row(name, one_thread, reference):
        return {"operation": name, "cutfem_one_thread": one_thread, "reference_time": reference,
                "per_thread": reference / one_thread}

    refs = [row("the cut stage (band, S_h), whole", 1.0, 2.0), row("the matrix stage, whole", 3.0, 1.0),
            row("K X, 3 columns, double", 1.0, 2.0), row("Gauss-Seidel sweep from zero, 3 columns", 1.5, 1.0),
            row("Galerkin P^T K P, first level", 1.0, 1.0), row("active-node numbering", 9.0, 1.0),
            row("the topology stage (interior faces), whole", 1.0, 4.0), row("the right-hand sides, whole", 5.0, 2.0)]
    t = performance_bounds.stage_targets([coarse, fine], refs)
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
    assert "exact_share" not in performance_bounds.stage_targets([coarse, fine], refs)["errors"]  # not recorded
    assert performance_bounds.stage_targets([], refs) == {}


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
    b = performance_bounds.stage_bounds(rec, 1e10)
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
    warm = performance_bounds.stage_bounds(_fabricated_level(warm={"time": {k: v / 2 for k, v in rec["time"].items()}}), 1e10)
    for stage in ("cut", "topology", "matrix", "rhs", "solve", "errors"):
        assert warm[stage]["ratio"] == pytest.approx(5.0) and warm[stage]["ratio_fresh"] == pytest.approx(10.0), stage
        assert warm[stage]["measured"] == rec["time"][stage] / 2 and warm[stage]["measured_fresh"] == rec["time"][stage]
    # a direct solve (no iterations): K read once and the 500 x 3 solution written
    direct = performance_bounds.stage_bounds(_fabricated_level(iterations=0), 1e10)["solve"]
    assert direct["bytes"] == 12 * 8000 + 24 * 500 and "direct" in direct["bound_method"]
    with pytest.raises(ValueError, match="bandwidth"):
        performance_bounds.stage_bounds(rec, 0.0)


def test_memory_bandwidth_is_a_plausible_rate():
    bw = performance_bounds.memory_bandwidth(16, repeat=2)
    assert 1e8 < bw["copy"] < 1e12 and 1e8 < bw["triad"] < 1e12
    assert bw["bandwidth"] == max(bw["copy"], bw["triad"]) and "best of 2" in bw["method"]
    two = performance_bounds.memory_bandwidth(16, repeat=2, threads=2)
    assert two["threads"] == 2 and "2 thread(s)" in two["method"] and 1e8 < two["copy"] < 1e12


def test_the_topology_reference_matches_the_same_faces():
    """VTK's geometry filter, the topology stage's reference, keeps exactly the faces of the active
    tets that the interior faces leave unpaired (cut torus at spacing 0.2, as sorted node triples)."""
    import pyvista as pv

    from cutfem.geometry.cut import CUT, cut_mesh
    from cutfem.geometry.shapes import Torus
    from cutfem.geometry.markers import interior_facets
    from cutfem.geometry.box import structured_box
    from cutfem.geometry.numbering import TET_FACES

    es = cut_mesh(structured_box(*performance_levels.BOX, spacing=0.2), Torus(1.0, 0.5)).elements(CUT)
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
    rows = performance_bounds.compiled_references(0.2, repeat=1)
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
