"""cutfem.studies.peers_order2 and peers_ngsxfem_order2: the order-2 comparison with ngsxfem.

What needs ngsolve and xfem is skipped without them (the ``ngsxfem`` fixture,
tests/studies/conftest.py); the "peer absent" path and the guard of the cutfem column are tested always.
"""

import json

import numpy as np
import pytest

from cutfem.runs.registry import get_problem
from cutfem.studies import peers_ngsxfem_order2 as peer2
from cutfem.studies import peers_order2


def test_run_without_peer_writes_a_note_and_skips(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(peers_order2, "peer_missing", lambda: "ModuleNotFoundError: No module named 'ngsolve'")
    assert peers_order2.run(tmp_path, "tiny", None) == {"skipped": 'install with pip install -e ".[peers]"'}
    assert 'pip install -e ".[peers]"' in capsys.readouterr().out
    data = json.loads((tmp_path / "peers_order2.json").read_text())
    assert data["available"] is False and "ngsolve" in data["reason"]


def test_cutfem_column_follows_the_order_parameter():
    """The cutfem column runs exactly when the problem takes ``order``, with the peer's parameters it has."""
    for name, spec in peers_order2.PROBLEMS.items():
        params = get_problem(spec["cutfem"]).param_map()
        missing = peers_order2.cutfem_order2_missing(name)
        assert missing == (None if "order" in params else peers_order2.CUTFEM_MISSING)
        assert set(peers_order2.cutfem_params(name)) == set(spec["params"]) & set(params)


def test_rates_and_rows_with_a_missing_column():
    levels = [{"problem": "poisson", "spacing": s, "cutfem": {"note": peers_order2.CUTFEM_MISSING},
               "ngsxfem": {"l2_error": e, "h1_error": 10 * e, "volume_error": e, "dofs": n, "total": 1.0, "time": {"solve": 1.0}}}
              for s, e, n in ((0.2, 8e-3, 10), (0.1, 1e-3, 80))]
    rows = peers_order2.table_rows(levels)
    ng = [r for r in rows if r["code"] == "ngsxfem"]
    assert ng[0]["l2_error_rate"] is None and ng[1]["l2_error_rate"] == pytest.approx(3.0)
    cf = [r for r in rows if r["code"] == "cutfem"]
    assert all(r["note"] == peers_order2.CUTFEM_MISSING and r["l2_error"] is None for r in cf)
    header, body = peers_order2.latex_rows(rows)
    assert all(len(b) == len(header) for b in body)


def test_a_failing_cutfem_level_is_recorded_and_the_peer_still_runs(monkeypatch):
    def process(code, problem, spacing):
        if code == "cutfem":
            raise RuntimeError("poisson cutfem spacing 0.2 failed:\nProblemError: ...")
        return {"l2_error": 1e-3, "dofs": 10}

    monkeypatch.setattr(peers_order2, "cutfem_order2_missing", lambda problem: None)
    monkeypatch.setattr(peers_order2, "_process", process)
    c = peers_order2.compare_level("poisson", 0.2)
    assert c["cutfem"]["note"] == "cutfem failed" and "ProblemError" in c["cutfem"]["failure"]
    assert c["ngsxfem"] == {"l2_error": 1e-3, "dofs": 10}


def test_levelset_and_sphere_solution_match_cutfem(ngsxfem):
    """levelset_cf is cutfem's phi (sphere and shifted torus); sphere_solution_cf is laplace-beltrami-cut's u, f, grad_S u."""
    from cutfem.geometry.box import structured_box
    from cutfem.geometry.shapes import Sphere, Torus
    from cutfem.problems.laplace_beltrami import SphereSolution
    from cutfem.studies.peers_ngsxfem import ngsolve_mesh

    mesh = ngsolve_mesh(structured_box([-2, -2, -1], [2, 2, 1], cells=2))
    pts = np.array([[0.3, -0.2, 0.5], [-0.7, 0.6, 0.1], [1.2, 0.9, -0.4]])

    def at(cf):
        return np.array([cf(mesh(*p)) for p in pts])

    for shape in (Sphere(radius=0.9, center=(0.1, 0, 0)), Torus(center=(0.05, -0.1, 0.02))):
        assert np.allclose(at(peer2.levelset_cf(shape)), shape.value(pts), rtol=1e-13, atol=1e-14)
    u, f, grad_s = peer2.sphere_solution_cf(1.3)
    sol = SphereSolution(1.3)
    assert np.allclose(at(u), sol.u(pts), rtol=1e-13, atol=1e-14)
    assert np.allclose(at(f), sol.f(pts), rtol=1e-13, atol=1e-14)
    assert np.allclose(at(grad_s).reshape(-1, 3), sol.grad(pts), rtol=1e-12, atol=1e-14)


def test_peer_poisson_order2_rate(ngsxfem):
    """P2 on ngsxfem's isoparametric cut of the unit ball: L2 error rate > 2.5 from spacing 0.2 to
    0.1 (measured 3.03; H1 1.99)."""
    coarse, fine = (peer2.ngsxfem_poisson_p2(s) for s in (0.2, 0.1))
    for key, least in (("l2_error", 2.5), ("h1_error", 1.7)):
        assert np.log2(coarse[key] / fine[key]) > least
    assert fine["volume_error"] < 1e-4  # |Omega_h| of the deformed cut: 5.4e-5
    assert fine["solver_iterations"] < 2000


@pytest.mark.slow  # 6 s today (the peer's two levels, each a fresh process); cutfem's order-2 levels join it once they exist
def test_study_tiny_poisson_writes_the_table(ngsxfem, tmp_path):
    summary = peers_order2.run(tmp_path, "tiny", None, problem="poisson")
    names = {p.name for p in tmp_path.iterdir()}
    assert {f"peers_order2.{ext}" for ext in ("json", "csv", "tex", "png", "pdf")} <= names
    data = json.loads((tmp_path / "peers_order2.json").read_text())
    assert data["available"] is True and data["order"] == 2
    ng = [r for r in summary["table"] if r["code"] == "ngsxfem"]
    assert [r["spacing"] for r in ng] == [0.2, 0.1]
    assert ng[1]["l2_error_rate"] > 2.5 and ng[1]["peak_memory_gib"] > 0
    cf = [r for r in summary["table"] if r["code"] == "cutfem"]
    if peers_order2.cutfem_order2_missing("poisson"):
        assert all(r["note"] == peers_order2.CUTFEM_MISSING for r in cf)
        assert peers_order2.CUTFEM_MISSING in (tmp_path / "peers_order2.tex").read_text()
