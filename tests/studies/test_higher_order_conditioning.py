"""Condition numbers over random positions of the surface (studies/shift_conditioning.py, part of the
higher-order study): at order 2 they grow like h^-2 and do not depend on the cut position beyond a
bounded factor; coarse spacings in the fast suite, the study's quick table in the slow one."""

import json

import numpy as np
import pytest

from cutfem.studies import shift_conditioning as sc


def test_order_two_condition_numbers_at_coarse_spacings():
    """The sphere's trace system with the normal-gradient stabilization (tau_N h, laplace-beltrami-cut's
    parameters) at orders 1 and 2, spacings 0.4 and 0.2, 6 positions each: the exponent p of
    max kappa ~ s^(-p) within 0.3 of 2 (measured 2.01 and 2.12) and max / min over the positions below
    1.5 (measured 1.02-1.08).  The face stabilization at order 2 grows faster (p about 3.6 here,
    kappa 3.2e5 and 4.0e6): see the slow test."""
    rows = sc.shift_rows([0.4, 0.2], systems=("sphere-normal",), orders=(1, 2), n_shifts=6)
    for order in (1, 2):
        p = sc.slopes(rows)[f"sphere-normal_order{order}"]["max"]
        assert abs(p - 2.0) < 0.3, (order, p, rows)
    for r in rows:
        assert r["ratio"] < 1.5 and r["not_definite"] == 0, r


def test_system_matrix_refuses_an_unknown_system():
    with pytest.raises(ValueError, match="unknown system 'cube'"):
        sc.system_matrix("cube", (0.0, 0.0, 0.0), 0.4, 1)
    with pytest.raises(ValueError, match="stabilization must be 'face' or 'normal'"):
        sc.sphere_matrix((0.0, 0.0, 0.0), 0.4, 1, "edge")


@pytest.mark.slow
def test_higher_order_conditioning_table(tmp_path):
    """The quick table: 20 positions, spacings 0.4, 0.2, 0.1, orders 1 and 2, the three systems;
    its files, and at order 2 the slope of max kappa between 1.5 and 2.5 and max / min below 10."""
    summary = sc.conditioning_outputs(tmp_path, "quick", [0.4, 0.2, 0.1])
    assert {f"{sc.NAME}.json", f"{sc.NAME}.csv", f"{sc.NAME}_table.tex", f"{sc.NAME}.png"} <= {p.name for p in tmp_path.iterdir()}
    data = json.loads((tmp_path / f"{sc.NAME}.json").read_text())
    assert len(data["rows"]) == 3 * 2 * 3 and all(len(r["kappas"]) == sc.N_SHIFTS for r in data["rows"])
    for system in sc.SYSTEMS:
        p = summary["slopes"][f"{system}_order2"]["max"]
        assert 1.5 < p < 2.5, (system, p)
    assert max(r["ratio"] for r in summary["rows"] if r["order"] == 2) < 10
    assert np.all([r["not_definite"] == 0 for r in summary["rows"]])
