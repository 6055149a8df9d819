"""Condition numbers over random positions of the surface (studies/shift_conditioning.py, part of the
higher-order study): at order 2 they grow like h^-2 and do not depend on the cut position beyond a
bounded factor; coarse spacings in the fast suite, the study's quick table in the slow one."""

import json

import numpy as np
import pytest

from cutfem.studies import shift_conditioning as sc


def test_order_two_condition_numbers_at_coarse_spacings():
    """The sphere's trace system with the normal-gradient stabilization (laplace-beltrami-cut's: tau_N h at
    order 1, tau_N h^-1 at order 2, its order-2 default) at spacings 0.4 and 0.2, 6 positions each: the
    exponent p of max kappa ~ s^(-p) within 0.4 of 2 and max / min over the positions below 1.5.  The
    mean curvature system with mean-curvature-cut's order-2 default (face a = 1 plus tau_N h J_N): p
    at most 2.4 (it grows like h^-1 there).  The face stabilization alone at order 2 grows faster
    (p about 3.6 here, kappa 3.2e5 and 4.0e6): see the slow test."""
    rows = sc.shift_rows([0.4, 0.2], systems=("sphere-normal",), orders=(1, 2), n_shifts=6)
    rows += sc.shift_rows([0.4, 0.2], systems=("sphere-mcv",), orders=(2,), n_shifts=6)
    fits = sc.slopes(rows)
    for order in (1, 2):
        p = fits[f"sphere-normal_order{order}"]["max"]
        assert abs(p - 2.0) < 0.4, (order, p, rows)
    assert fits["sphere-mcv_order2"]["max"] < 2.4, fits
    for r in rows:
        assert r["ratio"] < 1.5 and r["not_definite"] == 0, r
    assert [r["default"] for r in rows if r["system"] == "sphere-normal"] == [False, False, True, True]


def test_system_matrix_refuses_an_unknown_system():
    with pytest.raises(ValueError, match="unknown system 'cube'"):
        sc.system_matrix("cube", (0.0, 0.0, 0.0), 0.4, 1)
    with pytest.raises(ValueError, match="stabilization must be 'face' or 'normal'"):
        sc.sphere_matrix((0.0, 0.0, 0.0), 0.4, 1, "edge")


@pytest.mark.slow
def test_higher_order_conditioning_sphere_and_files(tmp_path):
    """The sphere at spacings 0.4, 0.2, 0.1, 20 positions: at order 2 the normal-gradient
    stabilization (tau_N h^-1, the order-2 default) gives kappa ~ h^-2 (measured p = 2.02) and the face stabilization does not (p =
    3.85: kappa 3.2e5, 4.2e6, 6.6e7), both within a factor 1.5 over the positions.  Then the files
    and the ball at 0.4, 0.2 (kappa about 1e4 at order 2, max / min 1.60 and 1.31)."""
    rows = sc.shift_rows([0.4, 0.2, 0.1], systems=("sphere-face", "sphere-normal"), orders=(2,))
    fits = sc.slopes(rows)
    assert 1.8 < fits["sphere-normal_order2"]["max"] < 2.4 and fits["sphere-face_order2"]["max"] > 3.5, fits
    assert all(r["ratio"] < 1.5 and r["not_definite"] == 0 for r in rows), rows
    summary = sc.conditioning_outputs(tmp_path, "tiny", [0.4, 0.2])
    assert {f"{sc.NAME}.json", f"{sc.NAME}.csv", f"{sc.NAME}_table.tex", f"{sc.NAME}.png"} <= {p.name for p in tmp_path.iterdir()}
    data = json.loads((tmp_path / f"{sc.NAME}.json").read_text())
    assert len(data["rows"]) == len(sc.SYSTEMS) * 2 * 2 and all(len(r["kappas"]) == sc.N_SHIFTS for r in data["rows"])
    ball = [r for r in summary["rows"] if r["system"] == "ball" and r["order"] == 2]
    assert all(5e3 < r["kappa_max"] < 3e4 and r["ratio"] < 2.0 and r["not_definite"] == 0 for r in ball), ball
    assert np.all([r["ratio"] < 2.0 for r in summary["rows"]])
