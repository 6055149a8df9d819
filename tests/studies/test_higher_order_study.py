"""The geometry table of the higher-order study (studies/higher_order.py) at the tiny size: its files,
and the order of each geometry error (order 2 at least one order better than order 1)."""

import json

from cutfem.studies import higher_order


def test_higher_order_geometry_table(tmp_path, capsys):
    summary = higher_order.run(tmp_path, "tiny", None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["higher_order_geometry.csv", "higher_order_geometry.json",
                                                          "higher_order_geometry_table.tex"]
    data = json.loads((tmp_path / "higher_order_geometry.json").read_text())
    assert len(data["rows"]) == 3 * 2 * 2  # three surfaces, two orders, spacings 0.2 and 0.1
    for surface in ("sphere", "torus", "ellipsoid"):
        flat, lifted = summary["last_rates"][f"{surface}_order1"], summary["last_rates"][f"{surface}_order2"]
        assert 1.7 < flat["area"] < 2.5 and 1.7 < flat["distance"] < 2.5, flat
        assert lifted["area"] > 3.0 and lifted["volume"] > 3.0 and lifted["distance"] > 2.8, lifted
    assert "higher_order_geometry_table.tex" in capsys.readouterr().out
