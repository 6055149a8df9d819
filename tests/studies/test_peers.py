"""cutfem.studies.peers: cutfem beside ngsxfem (NGSolve + xfem) on the identical cut mean curvature,
fictitious-domain Poisson and cut Stokes problems.

The comparisons need the optional peers (``pip install -e ".[peers]"``) and are skipped without
them (the ``ngsxfem`` fixture, tests/studies/conftest.py); the "peer absent" path is tested always.
"""

import json

import pytest

from cutfem.studies import peers


def test_run_without_peer_writes_a_note_and_skips(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(peers, "peer_missing", lambda: "ModuleNotFoundError: No module named 'ngsolve'")
    summary = peers.run(tmp_path, "tiny", None)
    assert summary == {"skipped": 'install with pip install -e ".[peers]"'}
    assert 'pip install -e ".[peers]"' in capsys.readouterr().out
    data = json.loads((tmp_path / "peers.json").read_text())
    assert data["available"] is False and "ngsolve" in data["reason"]


def test_tiny_comparison_agrees_to_three_digits(ngsxfem):
    c = peers.compare_level(0.2, "paper")
    cf, ng = c["cutfem"], c["ngsxfem"]
    assert c["same_problem"]  # same active tets, ghost faces and unknowns
    assert ng["area"] == pytest.approx(cf["area"], rel=1e-12)
    assert c["rel_diff"] < 5e-4  # 3 significant digits (measured: 2.4e-7, the two degree-4 rules)
    assert c["significant_digits"] > 3
    assert ng["superlu_vs_native"] < 1e-10  # the same system, solved by both direct solvers
    for code in (cf, ng):
        assert code["total"] > 0 and all(t >= 0 for t in code["time"].values())


def test_zero_nodal_values_and_their_rules(ngsxfem):
    """Spacing 0.1 has nodes exactly on the torus: ngsxfem 2.1 refuses them; with the zeros made
    +eps and cutfem's active set it agrees, and with the torus shifted off the nodes too."""
    c = peers.compare_level(0.1, "paper")
    assert c["ngsxfem"]["zero_nodes"] > 0
    if "ngsxfem_failed" in c:
        assert "lset" in c["ngsxfem_failed"]
        v = c["variants"]
        assert v["+eps"]["active_tets"] > c["cutfem"]["active_tets"]  # collapsed pieces kept
        assert v["+eps-cutfem-active"]["dropped_collapsed_tets"] > 0
    assert c["same_problem"] and c["rel_diff"] < 5e-4
    s = peers.compare_level(0.1, "shifted")
    assert s["ngsxfem"]["zero_nodes"] == 0 and "ngsxfem_failed" not in s
    assert s["same_problem"] and s["rel_diff"] < 5e-4


def test_study_tiny(ngsxfem, tmp_path):
    summary = peers.run(tmp_path, "tiny", None)
    names = {p.name for p in tmp_path.iterdir()}
    for stem in peers.OUTPUTS:
        assert any(n.startswith(stem + ".") for n in names)
    assert {"peers.png", "peers.pdf", "peers.json", "peers.csv", "peers_meshed.csv"} <= names
    assert all(n.startswith(peers.NAME) for n in names)
    data = json.loads((tmp_path / "peers.json").read_text())
    assert data["available"] is True
    row = summary["table"][0]
    assert row["rel_diff"] < 5e-4 and row["time_ratio"] > 0
    meshed = data["meshed"]
    assert {r["family"] for r in meshed} == set(peers.FAMILIES)
    assert {r["method"] for r in meshed} == {"cotan-voronoi", "stabilized"}
    assert all(r["discrete_error"] > 0 and r["seconds"] > 0 for r in meshed)


def test_poisson_same_problem_and_errors(ngsxfem):
    """Spacing 0.1 (the box [-1.1, 1.1]^3: nodes on the sphere included): the same unknowns, active
    tets, cut tets and ghost faces, the same volume of Omega_h, and L2/H1 errors within 1e-4 (the
    two codes place their quadrature points differently in the cut tets)."""
    c = peers.compare_poisson_level(0.1)
    cf, ng = c["cutfem"], c["ngsxfem"]
    assert ng["zero_nodes"] > 0 and ng["dropped_collapsed_tets"] > 0
    assert c["same_problem"]
    assert ng["dofs"] == cf["dofs"] and ng["active_tets"] == cf["active_tets"]
    assert c["rel_diff_volume"] < 1e-10
    assert c["rel_diff_l2"] < 1e-4 and c["rel_diff_h1"] < 1e-4


def test_poisson_study_tiny_writes_json_and_table(ngsxfem, tmp_path, capsys):
    assert peers.main(["--problem", "poisson", "--tiny", "--quiet", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "peers_poisson.json").read_text())
    row = data["table"][0]
    assert data["available"] and row["same_problem"] and row["time_ratio"] > 0
    assert {p.name for p in tmp_path.iterdir()} == {"peers_poisson.json", "peers_poisson.csv"}
    assert "L2 ngsxfem" in capsys.readouterr().out


def test_stokes_without_peer_writes_a_note_and_skips(tmp_path, monkeypatch):
    monkeypatch.setattr(peers, "peer_missing", lambda: "ModuleNotFoundError: No module named 'ngsolve'")
    assert peers.run_stokes(tmp_path, "tiny", None) == {"skipped": 'install with pip install -e ".[peers]"'}
    assert json.loads((tmp_path / "peers_stokes.json").read_text())["available"] is False


def test_stokes_study_tiny_same_problem_and_errors(ngsxfem, tmp_path, capsys):
    """Spacing 0.2, each code in a fresh process: the same unknowns, active tets and ghost faces, and
    the three errors (L2 and H1 of the velocity, L2 of the pressure) within 1e-6 relative (measured:
    7e-9; the codes place their quadrature points differently in the cut tets, and ngsxfem's MINRES
    stops at a relative residual of 1e-8); times and peak memories recorded for both."""
    assert peers.main(["--problem", "stokes", "--tiny", "--quiet", "--out", str(tmp_path)]) == 0
    assert {p.name for p in tmp_path.iterdir()} == {"peers_stokes.json", "peers_stokes.csv"}
    data = json.loads((tmp_path / "peers_stokes.json").read_text())
    row = data["table"][0]
    assert data["available"] and row["same_problem"] and row["dofs"] == 4041
    assert max(row["rel_diff_l2u"], row["rel_diff_h1u"], row["rel_diff_l2p"]) < 1e-6
    assert row["l2u_cutfem"] == pytest.approx(0.0208706, rel=1e-5)  # the level's record (stokes-cut at spacing 0.2)
    for code in ("cutfem", "ngsxfem"):
        assert row[f"time_{code}"] > 0 and row[f"memory_{code}_gib"] >= row[f"start_memory_{code}_gib"] > 0
    assert row["ngsxfem_solver"] == "minres" and 0 < row["ngsxfem_iterations"] < 100
    assert "L2 u cutfem" in capsys.readouterr().out
