"""The solver study (studies.solvers): its outputs at the tiny size, the multigrid iterations on the
bulk problems, the iterative solutions against the direct ones, and how it skips and records
failures."""

from __future__ import annotations

import csv
import json

import pytest

from cutfem.solvers.solve import DIRECT_LIMIT
from cutfem.studies import solvers as st

BULK = ("poisson-cut", "interface-poisson-cut 1:1", "interface-poisson-cut 1:1000", "bulk-surface-cut")
#: CG with geometric multigrid to a relative residual of 1e-8: 10-12 iterations measured at the finer tiny level
MG_MAX_ITERATIONS = 30


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("solvers")
    return out, st.run(out, "tiny")


def _rows(summary, case, solver):
    return [r for r in summary["rows"] if r["case"] == case and r["solver"] == solver]


@pytest.mark.slow  # the tiny study: 7 s warm, 18 s with its kernels compiled
def test_study_writes_its_outputs(tiny):
    out, summary = tiny
    for suffix in (".json", ".csv", ".png", ".pdf"):
        assert (out / f"{st.NAME}{suffix}").stat().st_size > 0
    assert (out / f"{st.NAME}.png").read_bytes()[:4] == b"\x89PNG"
    data = json.loads((out / f"{st.NAME}.json").read_text())
    assert data["complete"] is True
    cases = {c["key"]: c for c in data["cases"]}
    # every problem with a system solver, the heat equation (a solve a time step) left out
    assert set(cases) == set(BULK) | {"poisson-cut tetwild", "laplace-beltrami-cut", "mean-curvature-cut",
                                      "laplace-beltrami-meshed", "mean-curvature-meshed"}
    assert "heat-surface-cut" not in {c["problem"] for c in data["cases"]}
    for c in data["cases"]:
        assert c["solvers"] == ["auto", "direct", "cg-mg", "cg-amg", "cg-jacobi"]
    # one row per case, solver and level
    assert len(data["rows"]) == sum(len(c["solvers"]) * len(c["levels"]) for c in data["cases"])
    with (out / f"{st.NAME}.csv").open() as fh:
        assert len(list(csv.DictReader(fh))) == len(data["rows"])
    for r in data["rows"]:
        if r["status"] == "ok":
            assert r["dofs"] > 0 and r["solve_s"] >= 0 and r["total_s"] >= r["solve_s"]
            assert r["solve_s_per_M"] == pytest.approx(r["solve_s"] / r["dofs"] * 1e6, rel=2e-5)  # six-digit JSON (studies.common.save_json)
            if r["solver"] != "auto":
                assert r["method"] == r["solver"]
            elif r["case"] != "poisson-cut tetwild":  # a structured background or a surface mesh: a hierarchy
                assert r["method"] == ("direct" if r["dofs"] <= DIRECT_LIMIT else "cg-mg")
            assert (r["iterations"] == 0) == (r["method"] == "direct")


@pytest.mark.slow  # the tiny study: 7 s warm, 18 s with its kernels compiled
def test_cg_mg_without_a_lattice_is_recorded_as_an_error(tiny):
    _, summary = tiny
    (row,) = _rows(summary, "poisson-cut tetwild", "cg-mg")
    assert row["status"] == "error" and "geometric hierarchy" in row["error"]
    # every other combination of the tiny size runs
    others = [r for r in summary["rows"] if r is not row]
    assert all(r["status"] == "ok" for r in others), [r for r in others if r["status"] != "ok"]


@pytest.mark.slow
@pytest.mark.parametrize("case", BULK)
def test_multigrid_iterations_on_the_bulk_problems(tiny, case):
    _, summary = tiny
    rows = _rows(summary, case, "cg-mg")
    assert len(rows) == 2 and all(r["status"] == "ok" and r["method"] == "cg-mg" for r in rows)
    assert all(1 <= r["iterations"] <= MG_MAX_ITERATIONS for r in rows), [r["iterations"] for r in rows]
    # the finer level iterates (its coarsest grid is not the whole problem)
    assert rows[-1]["iterations"] >= 3


@pytest.mark.slow  # the tiny study: 7 s warm, 18 s with its kernels compiled
def test_iterative_solutions_equal_the_direct_ones(tiny):
    # the same discrete problem (structured backgrounds and meshes are deterministic): the errors
    # of the iterative solutions (relative residual 1e-8) agree with the direct solve's
    _, summary = tiny
    compared = 0
    for case in {r["case"] for r in summary["rows"]} - {"poisson-cut tetwild"}:
        direct = {r["level"]: r for r in _rows(summary, case, "direct")}
        for solver in ("cg-mg", "cg-amg", "cg-jacobi"):
            for r in _rows(summary, case, solver):
                d = direct[r["level"]]
                assert r["dofs"] == d["dofs"]
                keys = [k for k in d if "_error" in k and d[k] is not None]
                assert keys, case
                for k in keys:
                    assert r[k] == pytest.approx(d[k], rel=1e-6), (case, solver, r["level"], k)
                    compared += 1
    assert compared >= 50


def test_predicted_unknowns_and_skips():
    bulk = {"dim": 3, "level_name": "spacing"}
    meshed = {"dim": 2, "level_name": "n"}
    assert st.predicted_dofs(bulk, 0.05, {}) is None
    assert st.predicted_dofs(bulk, 0.05, {0.1: 1000, 0.2: 130}) == 8000  # from the finest level, h^-3
    assert st.predicted_dofs(bulk, 0.1, {0.1: 1234}) == 1234  # measured
    assert st.predicted_dofs(meshed, 64, {16: 162, 32: 642}) == 2568  # n^2
    assert st.skip_reason(bulk, "direct", st.DIRECT_BULK_LIMIT) is None
    assert "direct above" in st.skip_reason(bulk, "direct", st.DIRECT_BULK_LIMIT + 1)
    assert st.skip_reason(meshed, "direct", st.DIRECT_BULK_LIMIT + 1) is None  # surface systems go further
    assert "cg-jacobi above" in st.skip_reason(meshed, "cg-jacobi", st.JACOBI_LIMIT + 1)
    assert "cg-amg above" in st.skip_reason(meshed, "cg-amg", st.AMG_SURFACE_LIMIT + 1)
    assert st.skip_reason(bulk, "cg-amg", st.AMG_SURFACE_LIMIT + 1) is None  # bulk systems: 8-48 iterations
    assert st.skip_reason(bulk, "cg-mg", 10**9) is None and st.skip_reason(bulk, "direct", None) is None


def test_a_case_skips_by_the_unknowns_of_auto_and_stops_after_a_failure(monkeypatch):
    monkeypatch.setattr(st, "DIRECT_BULK_LIMIT", 500)
    case = {"key": "p", "problem": "poisson-cut", "params": {}, "levels": [0.4, 0.2], "dim": 3, "solvers": ["auto", "direct"],
            "level_name": "spacing"}
    rows = st.study_case(case)
    assert [(r["solver"], r["status"]) for r in rows] == [("auto", "ok"), ("auto", "ok"), ("direct", "ok"), ("direct", "skipped")]
    assert rows[3]["dofs"] == rows[1]["dofs"] > 500 and "direct above 500" in rows[3]["reason"]
    # a parameter the problem refuses: the error is kept and the finer level is not tried
    bad = dict(case, params={"background": "hexahedra"}, solvers=["cg-mg"])
    rows = st.study_case(bad)
    assert [r["status"] for r in rows] == ["error", "skipped"]
    assert "hexahedra" in rows[0]["error"] and rows[1]["reason"] == "failed at spacing 0.4"
    text = st.table(rows)
    assert "error: ProblemError" in text and "skipped: failed at spacing 0.4" in text
