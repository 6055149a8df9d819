"""The benchmark note of the cut by several level sets (studies/csg_cut.py) at the tiny size: its
files, and the numbers every row must hold whatever the machine's speed (timings themselves are not
asserted: they belong to the machine and its load)."""

import json

import pytest

from cutfem.studies import csg_cut


def test_csg_cut_study_writes_its_table(tmp_path, capsys):
    summary = csg_cut.run(tmp_path, "tiny", None)
    data = json.loads((tmp_path / "csg_cut.json").read_text())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["csg_cut.json", "csg_cut_table.tex"]
    (row,) = data["rows"]
    assert row["spacing"] == 0.2 and row["tets"] == 10368
    # the ball alone and as a domain of one level set cut the same tets
    assert row["csg1_cut_tets"] == row["one_cut_tets"]
    for m in (1, 2, 3, 7):
        assert row[f"csg{m}"] > 0 and row[f"ratio{m}"] == pytest.approx(row[f"csg{m}"] / (m * row["one"]), rel=1e-5)
    # the JSON holds six significant digits, the summary the whole number
    assert summary["worst_ratio_per_level_set"] == pytest.approx(max(row[f"ratio{m}"] for m in (1, 2, 3, 7)), rel=1e-5)
    assert "csg_cut_table.tex" in capsys.readouterr().out
