"""The vector assembly benchmark (studies/vector_assembly.py) runs at its tiny size and records
what it promises: the three systems on one cut, 3 n unknowns beside n, positive times and the
ratios per unknown (no bound on the times: speed goals are met in benchmarks, not in tests)."""

import json

from cutfem.studies import vector_assembly


def test_vector_assembly_runs_and_records(tmp_path, capsys):
    assert vector_assembly.main(["--tiny", "--out", str(tmp_path), "--repeat", "1", "--quiet"]) == 0
    data = json.loads((tmp_path / "vector_assembly.json").read_text())
    (row,) = data["rows"]
    n = row["poisson_unknowns"]
    assert row["spacing"] == 0.2 and row["vector_laplacian_unknowns"] == row["elasticity_unknowns"] == 3 * n > 0
    for name in vector_assembly.SYSTEMS:
        total = row[f"{name}_matrix_seconds"] + row[f"{name}_rhs_seconds"]
        assert abs(row[f"{name}_seconds"] - total) <= 1e-5 * total  # the JSON keeps six digits
        assert row[f"{name}_matrix_seconds"] > 0 and row[f"{name}_rhs_seconds"] > 0
    assert row["elasticity_ratio"] > 0 and row["vector_laplacian_ratio"] > 0
    assert (tmp_path / "vector_assembly.csv").stat().st_size > 0
    assert "elast. ratio" in capsys.readouterr().out
