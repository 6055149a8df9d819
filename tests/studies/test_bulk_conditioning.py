"""Conditioning of fictitious-domain Poisson (studies.bulk_conditioning): the condition numbers it
records, on matrices with a known spectrum, the robustness of the ghost-penalty method over grid positions, its
loss without ghost penalty or with a too small Nitsche penalty, and the study's outputs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.sparse as sp

from cutfem.studies import bulk_conditioning as bc

# the ball at spacing 0.4 (about 200 unknowns) in six random positions of the study's seed
SPACING, N_SHIFTS = 0.4, 6


def _laplacian_1d(n, shift=0.0):
    """tridiag(-1, 2 - shift, -1) of size n and its eigenvalues 2 - shift - 2 cos(k pi / (n + 1))."""
    T = sp.diags([-np.ones(n - 1), np.full(n, 2.0 - shift), -np.ones(n - 1)], [-1, 0, 1], format="csr")
    return T, 2.0 - shift - 2.0 * np.cos(np.arange(1, n + 1) * np.pi / (n + 1))


@pytest.mark.parametrize("n", [50, 600])  # the dense and the sparse route of condition_number
def test_condition_number_of_a_definite_matrix(n):
    T, ev = _laplacian_1d(n)
    r = bc.spectrum_record(T)
    assert r["kappa"] == pytest.approx(ev.max() / ev.min(), rel=1e-6)
    assert r["lambda_max"] == pytest.approx(ev.max() / 2, rel=1e-7)  # D = 2 I
    assert not r["indefinite"] and not r["singular"] and r["negative_diagonal"] == 0


@pytest.mark.parametrize("n", [50, 600])
@pytest.mark.parametrize("shift", [0.5, 1.9, 2.5])
def test_condition_number_of_indefinite_matrices(n, shift):
    # a diagonal of 2 - shift, negative for shift = 2.5: |D| keeps the inertia
    T, ev = _laplacian_1d(n, shift)
    r = bc.spectrum_record(T)
    assert r["indefinite"] and np.isfinite(r["kappa"])
    assert r["negative_diagonal"] == (n if shift > 2 else 0)
    assert r["kappa"] == pytest.approx(np.abs(ev).max() / np.abs(ev).min(), rel=1e-5)


@pytest.fixture(scope="module")
def rows():
    return bc.shift_study(SPACING, N_SHIFTS, seed=bc.SEED)


def test_ghost_penalty_makes_kappa_independent_of_the_position(rows):
    s = bc.summarize(rows, "ghost")
    assert s["count"] == N_SHIFTS and s["indefinite"] == 0 and s["singular"] == 0
    assert s["ratio"] <= 2.0


def test_without_ghost_penalty_kappa_is_unbounded_and_the_matrix_indefinite(rows):
    # gamma = 10 without ghost penalty: on small cuts the Nitsche term loses coercivity, with
    # negative diagonal entries; measured: every one of the six positions is indefinite, ratio ~ 70
    g, s = bc.summarize(rows, "ghost"), bc.summarize(rows, "no_ghost")
    assert s["indefinite"] >= 1
    assert s["ratio"] > 10 and s["kappa_max"] > 10 * g["kappa_max"]


def test_too_small_nitsche_penalty_is_indefinite(rows):
    # gamma = 0.5 with ghost penalty: measured indefinite at all six positions
    assert bc.SMALL_GAMMA == 0.5
    s = bc.summarize(rows, "small_gamma")
    assert s["indefinite"] >= N_SHIFTS // 2


def test_fitted_exponent():
    s = np.array([0.4, 0.2, 0.1])
    assert bc.fitted_exponent(s, 3.0 * s**-2) == pytest.approx(2.0)
    assert bc.fitted_exponent(s, [np.inf, 5.0, 20.0]) == pytest.approx(2.0)
    assert bc.fitted_exponent(s, [np.inf, np.inf, 20.0]) is None


def test_study_writes_its_outputs(tmp_path):
    summary = bc.run(tmp_path, "tiny")
    data = json.loads((tmp_path / f"{bc.NAME}.json").read_text())
    for name in (f"{bc.NAME}.png", f"{bc.NAME}.pdf", f"{bc.NAME}_shifts.csv", f"{bc.NAME}_h.csv"):
        assert (tmp_path / name).stat().st_size > 0
    assert (tmp_path / f"{bc.NAME}.png").read_bytes()[:4] == b"\x89PNG"
    methods = data["shifts"]["methods"]
    assert set(methods) == {"ghost", "no_ghost", "small_gamma"}
    assert len(data["shifts"]["records"]) == 3 * data["shifts"]["count"]
    assert methods["ghost"]["ratio"] == pytest.approx(summary["ghost_ratio"], rel=5e-6)  # six-digit JSON (studies.common.save_json)
    assert methods["ghost"]["ratio"] <= 2.0 and methods["small_gamma"]["indefinite"] >= 1
    ref = data["refinement"]["records"]
    assert [r["spacing"] for r in ref] == summary["spacings"]
    assert ref[1]["dofs"] > 4 * ref[0]["dofs"]
    assert all(r["kappa_min"] <= r["kappa_median"] <= r["kappa_max"] and r["indefinite"] == 0 for r in ref)
    assert len(summary["exponent_local"]) == len(ref) - 1


@pytest.mark.parametrize("n", [50, 600])
def test_condition_number_of_a_singular_matrix(n):
    # the Neumann Laplacian: constants in the kernel
    T, _ = _laplacian_1d(n)
    T = T.tolil()
    T[0, 0] = T[n - 1, n - 1] = 1.0
    r = bc.spectrum_record(T.tocsr())
    assert r["singular"] and r["kappa"] > 1e12 and abs(r["lambda_nearest_zero"]) < 1e-10
