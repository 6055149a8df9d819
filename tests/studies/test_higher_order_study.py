"""The higher-order study (studies/higher_order.py) at the tiny size: its files, the order of each
geometry error (order 2 at least one order better than order 1), and the problems' L2 rates (P2 on the
lifted cut above 2.9, P1 below 2.6)."""

import json

import pytest

from cutfem.studies import higher_order


@pytest.mark.slow
def test_higher_order_geometry_table(tmp_path, capsys):
    summary = higher_order.run(tmp_path, "tiny", None)
    assert {"higher_order_geometry.csv", "higher_order_geometry.json", "higher_order_geometry_table.tex", "higher_order_problems.json",
            "higher_order_problems_table.tex", "higher_order_problems.png"} <= {p.name for p in tmp_path.iterdir()}
    data = json.loads((tmp_path / "higher_order_geometry.json").read_text())
    assert len(data["rows"]) == 3 * 2 * 2  # three surfaces, two orders, spacings 0.2 and 0.1
    for surface in ("sphere", "torus", "ellipsoid"):
        flat, lifted = summary["last_rates"][f"{surface}_order1"], summary["last_rates"][f"{surface}_order2"]
        assert 1.7 < flat["area"] < 2.5 and 1.7 < flat["distance"] < 2.5, flat
        assert lifted["area"] > 3.0 and lifted["volume"] > 3.0 and lifted["distance"] > 2.8, lifted
    assert "higher_order_geometry_table.tex" in capsys.readouterr().out
    problems = json.loads((tmp_path / "higher_order_problems.json").read_text())["rows"]
    last = {(r["problem"], r["order"]): r for r in problems}  # spacing 0.1
    for name in ("poisson-cut", "laplace-beltrami-cut", "mean-curvature-cut"):
        p1, p2 = last[name, 1], last[name, 2]
        assert p2["l2_error"] < 0.2 * p1["l2_error"] and p2["l2_error_rate"] > 2.9 and 1.3 < p1["l2_error_rate"] < 2.6, (p1, p2)
