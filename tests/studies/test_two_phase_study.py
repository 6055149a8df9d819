"""The two-phase study (studies/two_phase.py) runs at its tiny size and writes its files: one row per
route, viscosity ratio and level, the errors falling between the two levels."""

import json

import pytest

from cutfem.studies import two_phase


@pytest.mark.slow  # 5 s; the two routes of the problem are tested in tests/problems/test_two_phase_stokes.py
def test_two_phase_study_runs_and_records(tmp_path):
    assert two_phase.main(["--tiny", "--out", str(tmp_path), "--quiet"]) == 0
    data = json.loads((tmp_path / "two_phase.json").read_text())
    rows = data["rows"]
    assert len(rows) == len(two_phase.ROUTES) * len(two_phase.RATIOS) * 2
    for coarse, fine in zip(rows[::2], rows[1::2]):
        assert (coarse["curvature"], coarse["mu_inside"], coarse["mu_outside"]) == (fine["curvature"], fine["mu_inside"], fine["mu_outside"])
        assert fine["pressure_jump_error"] < coarse["pressure_jump_error"] < 0.1
        assert fine["l2_error_velocity"] < 5e-3
    for stem in ("two_phase.png", "two_phase.pdf", "two_phase.csv", "two_phase_table.tex"):
        assert (tmp_path / stem).stat().st_size > 0
