"""The claims table of ``cutfem reproduce`` on hand-made study tables (no solving): every decidable
claim turns to "no" when its number is wrong, and a number that is not there (NaN, a study that
failed) is never reported as agreeing."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cutfem.studies import reproduce
from cutfem.studies.common import save_json

FAMILIES = ("structured", "flipped", "perturbed", "perturbed-flipped")
#: rates that agree with every claim
GOOD = {("structured", 0.1): 1.5, ("flipped", 0.1): 1.5, ("perturbed", 0.1): 1.4, ("perturbed-flipped", 0.1): 1.4,
        ("structured", 0.0): 2.0, ("flipped", 0.0): 0.0, ("perturbed", 0.0): 0.1, ("perturbed-flipped", 0.0): 0.05}


def _fit(h, e):
    return float(np.polyfit(np.log(h), np.log(e), 1)[0])


def _last(h, e):
    return float(math.log(e[-2] / e[-1]) / math.log(h[-2] / h[-1]))


def meshed_table(rates=GOOD, integral=1e-13, levels=(16, 32, 64)):
    h = [float((n * n // 2) ** -0.5) for n in levels]
    series = []
    for (fam, tau), rate in rates.items():
        e = [0.5 * (x / h[0]) ** rate for x in h]
        series.append({"family": fam, "tau_e": tau, "n": list(levels), "h": h, "discrete_error": e,
                       "rate_fit_discrete": _fit(h, e), "rate_last_discrete": _last(h, e),
                       "integral_H_max": [integral] * len(levels) if np.isscalar(integral) else list(integral)})
    return {"levels": list(levels), "series": series}


def cut_table(rate=1.3, area_rate=2.0, integral=1e-13, spacing=(0.2, 0.1, 0.05)):
    h = [0.4 * s for s in spacing]
    l2 = [0.5 * (x / h[0]) ** rate for x in h]
    area = [0.1 * (x / h[0]) ** area_rate for x in h]
    return {"spacing": list(spacing), "h": h, "l2_error": l2, "area_error": area,
            "rate_fit_l2": _fit(h, l2), "rate_last_l2": _last(h, l2), "rate_fit_area": _fit(h, area), "rate_last_area": _last(h, area),
            "rates_l2": [math.log(l2[i] / l2[i + 1]) / math.log(h[i] / h[i + 1]) for i in range(len(h) - 1)],
            "dofs": [100, 400, 1600], "nodes_on_surface": [0, 16, 32],
            "integral_H_max": [integral] * len(h) if np.isscalar(integral) else list(integral)}


def _tables(tmp_path: Path, meshed=None, cut=None, summary=None) -> Path:
    tables = tmp_path / "tables"
    tables.mkdir(exist_ok=True)
    for name, data in (("meshed_convergence", meshed), ("cut_convergence", cut), ("summary", summary)):
        if data is not None:  # as the studies save them: a NaN or an infinity becomes null
            save_json(tables, name, data)
    return tables


def _agrees(rows):
    return {r["claim"]: r["agrees"] for r in rows}


def test_the_right_numbers_agree_with_every_claim(tmp_path):
    rows = reproduce.claims(_tables(tmp_path, meshed_table(), cut_table()))
    decided = [r for r in rows if r["agrees"] is not None]
    assert len(rows) == 13 and len(decided) == 11
    assert all(r["agrees"] is True for r in decided)


@pytest.mark.parametrize(
    "meshed, cut, claim",
    [
        (meshed_table({**GOOD, ("structured", 0.1): 0.5}), cut_table(), "meshed, structured, $\\tau_E = 0.1$: $O(h)$"),
        (meshed_table({**GOOD, ("flipped", 0.1): 0.5}), cut_table(), "meshed, flipped, $\\tau_E = 0.1$: $O(h)$"),
        (meshed_table({**GOOD, ("perturbed", 0.1): 0.5}), cut_table(), "meshed, perturbed, $\\tau_E = 0.1$: $O(h)$"),
        (meshed_table({**GOOD, ("perturbed-flipped", 0.1): 0.5}), cut_table(), "meshed, perturbed-flipped, $\\tau_E = 0.1$: $O(h)$"),
        (meshed_table({**GOOD, ("structured", 0.0): 1.5}), cut_table(), "meshed, structured, $\\tau_E = 0$: superconvergence"),
        (meshed_table({**GOOD, ("flipped", 0.0): 1.0}), cut_table(), "meshed, flipped, $\\tau_E = 0$: no convergence"),
        (meshed_table(integral=1e-6), cut_table(), "meshed: $\\int_{S_h} H_h = 0$"),
        (meshed_table(), cut_table(rate=1.0), "cut, $\\tau_F = 0.1$: $L^2$ rate"),
        (meshed_table(), cut_table(rate=0.5), "cut, $\\tau_F = 0.1$: $O(h)$ (theory)"),
        (meshed_table(), cut_table(area_rate=1.0), "cut: area of $S_h$, $O(h^2)$"),
        (meshed_table(), cut_table(integral=1e-6), "cut: $\\int_{S_h} H_h = 0$"),
    ],
)
def test_a_wrong_number_disagrees(tmp_path, meshed, cut, claim):
    agrees = _agrees(reproduce.claims(_tables(tmp_path, meshed, cut)))
    assert agrees[claim] is False
    assert sum(a is False for a in agrees.values()) >= 1


@pytest.mark.parametrize("where", [0, 1, 2])
def test_a_nan_integral_never_agrees(tmp_path, where):
    """An integral of H_h that is NaN at any level (a failed solve) is not zero."""
    values = [1e-13, 1e-13, 1e-13]
    values[where] = float("nan")
    agrees = _agrees(reproduce.claims(_tables(tmp_path, meshed_table(integral=values), cut_table(integral=values))))
    assert agrees["meshed: $\\int_{S_h} H_h = 0$"] is False
    assert agrees["cut: $\\int_{S_h} H_h = 0$"] is False


def test_a_nan_integral_is_not_printed_as_zero(tmp_path):
    tables = _tables(tmp_path, meshed_table(), cut_table(integral=[1e-13, float("nan"), 1e-13]))
    rows = reproduce._claims_outputs(tables)
    numbers = (tables / "numbers.tex").read_text()
    assert "\\newcommand{\\cutIntegralMax}{--}" in numbers
    assert "\\newcommand{\\claimsAgree}{10}" in numbers and "\\newcommand{\\claimsTotal}{11}" in numbers
    assert [r["agrees"] for r in rows if r["claim"] == "cut: $\\int_{S_h} H_h = 0$"] == [False]


@pytest.mark.parametrize("fam, tau", [("structured", 0.1), ("structured", 0.0), ("flipped", 0.0)])
def test_a_missing_rate_never_agrees(tmp_path, fam, tau):
    """A fitted rate that is not a number (an error of 0 or NaN at some level: saved as null) is
    reported as disagreeing, not as a crash after the whole run nor as agreeing."""
    meshed = meshed_table()
    s = next(s for s in meshed["series"] if (s["family"], s["tau_e"]) == (fam, tau))
    s["rate_fit_discrete"] = float("nan")
    cut = cut_table()
    cut["rate_fit_l2"] = cut["rate_fit_area"] = float("-inf")
    tables = _tables(tmp_path, meshed, cut)
    rows = reproduce._claims_outputs(tables)
    agrees = _agrees(rows)
    assert sum(a is False for a in agrees.values()) == 4
    assert agrees["cut, $\\tau_F = 0.1$: $L^2$ rate"] is False and agrees["cut: area of $S_h$, $O(h^2)$"] is False
    assert "\\newcommand{\\claimsAgree}{7}" in (tables / "numbers.tex").read_text()


@pytest.mark.parametrize("status", ["failed", None])
def test_numbers_of_a_study_that_did_not_run_are_not_used(tmp_path, status):
    """The tables folder keeps the JSON of an earlier run when a study fails (or is missing) in
    this one: the claims say so and disagree instead of agreeing with the old numbers."""
    studies = {"paper_cut": {"status": "ok", "size": "quick"}}
    if status is not None:
        studies["paper_meshed"] = {"status": status, "size": "quick", "error": "MemoryError: out of memory"}
    tables = _tables(tmp_path, meshed_table(), cut_table(), {"size": "quick", "studies": studies})
    rows = reproduce._claims_outputs(tables)
    meshed = [r for r in rows if r["claim"].startswith("meshed")]
    assert [(r["claim"], r["agrees"]) for r in meshed] == [("meshed torus: no numbers from the last run", False)]
    assert meshed[0]["source"] == ("paper_meshed " + (status or "did not run"))
    assert [r["agrees"] for r in rows if r["claim"].startswith("cut")] == [True] * 4
    numbers = (tables / "numbers.tex").read_text()
    assert "\\newcommand{\\claimsAgree}{4}" in numbers and "\\newcommand{\\claimsTotal}{5}" in numbers
    assert "rateStructuredStab" not in numbers and "\\newcommand{\\rateCut}{1.30}" in numbers
    assert "\\textbf{no}" in (tables / "claims.tex").read_text()


def test_numbers_of_the_last_run_are_used(tmp_path):
    studies = {name: {"status": "ok", "size": "quick"} for name in ("paper_meshed", "paper_cut")}
    rows = reproduce.claims(_tables(tmp_path, meshed_table(), cut_table(), {"size": "quick", "studies": studies}))
    assert len(rows) == 13 and all(r["agrees"] in (True, None) for r in rows)


def test_the_size_names_every_size_in_the_tables(tmp_path):
    """After ``--only paper_cut --full`` on a quick run the tables mix sizes: the manuscript's
    size says so instead of naming the last run's alone."""
    studies = {"paper_meshed": {"status": "ok", "size": "quick"}, "paper_cut": {"status": "ok", "size": "full"},
               "conditioning": {"status": "ok", "size": "quick"}}
    tables = _tables(tmp_path, meshed_table(), cut_table(), {"size": "full", "studies": studies})
    reproduce._claims_outputs(tables)
    assert "\\newcommand{\\reproduceSize}{quick + full}" in (tables / "numbers.tex").read_text()
    studies["paper_meshed"]["size"] = "full"
    studies["conditioning"]["size"] = "full"
    tables = _tables(tmp_path, meshed_table(), cut_table(), {"size": "full", "studies": studies})
    reproduce._claims_outputs(tables)
    assert "\\newcommand{\\reproduceSize}{full}" in (tables / "numbers.tex").read_text()
