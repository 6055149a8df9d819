"""Outputs of ``cutfem reproduce`` that do not depend on the machine or the thread count: numbers
written to six significant digits, round-off quantities written as their bound, figures without
dates, versions or random ids, and timings only in the files listed as timing files."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from cutfem.runs.convergence import FIGURE_METADATA, new_figure, save_reproducible, significant
from cutfem.studies import conditioning, reproduce
from cutfem.studies.common import INPUT_KEYS, ROUNDOFF_INTEGRAL, fmt_roundoff, roundoff_zero, save_csv, save_json

from test_reproduce_claims import _tables, cut_table, meshed_table

ROOT = Path(__file__).resolve().parents[2]

#: pairs of values that two machines (or thread counts) computed for the same number: the tracked
#: paper/tables of one machine against a rerun on another, before this fix
SAME_NUMBER = [(0.06485192890820435, 0.06485192890820973),  # cut L2 error at spacing 0.025
               (1.1715556749031600, 1.1715556749031588),
               (0.040823602048202026, 0.04082360204796676),  # a rate near 0: 5.8e-12 relative
               (573569.7472352609, 573569.7472349625),  # a condition number: 5.2e-13 relative
               (0.08019261243667809, 0.0801926124366781)]  # one thread against two


# --- numbers --------------------------------------------------------------------------------------


def test_six_significant_digits_decimal_and_exact():
    assert significant(0.06485192890820435) == 0.0648519
    assert significant(573569.7472352609) == 573570.0
    assert significant(1.1505379982068575e-13) == 1.15054e-13
    assert significant(-2.4162795947466327) == -2.41628
    assert significant(0.00012345649) == 0.000123456 and significant(0.00012345651) == 0.000123457
    assert significant(1 / 3, digits=2) == 0.33
    assert repr(significant(0.1 + 0.2)) == "0.3"  # the shortest repr: what JSON and CSV print


def test_significant_keeps_what_is_not_a_float():
    data = {"n": np.int64(7), "ok": np.bool_(True), "name": "torus", "none": None, "nan": float("nan"), "inf": -math.inf,
            "levels": (16, 32), "h": np.array([1 / 3, 2e300]), "nested": [{"x": np.float32(0.1)}]}
    out = significant(data)
    assert out["n"] == 7 and type(out["n"]) is int
    assert out["ok"] is True and out["name"] == "torus" and out["none"] is None
    assert math.isnan(out["nan"]) and out["inf"] == -math.inf
    assert out["levels"] == (16, 32) and out["h"] == [0.333333, 2e300]
    assert out["nested"] == [{"x": 0.1}]


@pytest.mark.parametrize("digits", [0, 18, 2.5, "6"])
def test_significant_refuses_a_bad_number_of_digits(digits):
    with pytest.raises(ValueError, match="digits must be an integer from 1 to 17"):
        significant(1.0, digits)


@pytest.mark.parametrize("a, b", SAME_NUMBER)
def test_the_same_number_from_two_machines_is_written_with_the_same_bytes(tmp_path, a, b):
    for tag, x in (("a", a), ("b", b)):
        save_json(tmp_path / tag, "table", {"l2_error": [x, 2 * x], "rate": x / 3})
        save_csv(tmp_path / tag, "table", [{"h": 0.1, "l2_error": x}, {"h": 0.05, "l2_error": x / 4}])
    for name in ("table.json", "table.csv"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    assert json.loads((tmp_path / "a" / "table.json").read_text())["l2_error"][0] == significant(a)


def test_inputs_of_a_run_are_written_whole(tmp_path):
    """A spacing of 0.4/3 at six digits would be another mesh: the inputs (INPUT_KEYS) are kept."""
    spacing = [0.2, 0.4 / 3]
    save_json(tmp_path, "t", {"spacing": spacing, "dt": 0.5 / 3, "l2_error": [0.4 / 3, 0.1]})
    save_csv(tmp_path, "t", [{"spacing": s, "l2_error": s} for s in spacing])
    data = json.loads((tmp_path / "t.json").read_text())
    assert data["spacing"] == spacing and data["dt"] == 0.5 / 3 and data["l2_error"] == [0.133333, 0.1]
    assert (tmp_path / "t.csv").read_text().splitlines()[2] == f"{0.4 / 3!r},0.133333"
    assert {"spacing", "dt", "levels", "box"} <= INPUT_KEYS


def test_roundoff_quantities_are_written_as_their_bound():
    # |int H_h| of the same surface on two machines: 1.2e-13 and 8.8e-14 (the cut torus, spacing 0.2)
    assert roundoff_zero(1.1505379982068575e-13) == roundoff_zero(8.818293317780501e-14) == 0.0
    assert roundoff_zero([-1.0e-14, 3.7e-14, 2e-9]) == [0.0, 0.0, 2e-9]  # above the floor: news, kept
    assert math.isnan(roundoff_zero(float("nan")))
    assert ROUNDOFF_INTEGRAL == 1e-10
    assert fmt_roundoff(6.1e-13) == fmt_roundoff(0.0) == "$<10^{-10}$"
    assert fmt_roundoff(2.34e-9) == "2.3e-09"
    assert fmt_roundoff(None) == fmt_roundoff(float("nan")) == "--"


def test_claims_and_numbers_show_the_roundoff_bound_not_its_digits(tmp_path):
    tables = _tables(tmp_path, meshed_table(integral=5.2e-14), cut_table(integral=[1.2e-13, 1.6e-13, 6.1e-13]))
    reproduce._claims_outputs(tables)
    claims = (tables / "claims.tex").read_text()
    assert "meshed: $\\int_{S_h} H_h = 0$ & exact & $<10^{-10}$ &" in claims
    assert "cut: $\\int_{S_h} H_h = 0$ & exact & $<10^{-10}$ &" in claims
    assert "e-13" not in claims and "e-14" not in claims
    assert "\\newcommand{\\cutIntegralMax}{$10^{-10}$}" in (tables / "numbers.tex").read_text()


def test_a_singular_matrix_has_lambda_min_zero_and_an_infinite_condition_number():
    """The smallest eigenvalue of a singular matrix (here the Neumann Laplacian of a path, constants
    in its kernel) and the 'condition number' the solve module reports for it are round-off: they
    are written as 0 and infinity, not as digits that change with the machine."""
    n = 12
    main = np.full(n, 2.0)
    main[[0, -1]] = 1.0
    A = sp.diags([-np.ones(n - 1), main, -np.ones(n - 1)], [-1, 0, 1], format="csr")
    rec = conditioning._kappa(A)
    assert rec["singular"] and rec["kernel_dimension"] == 1
    assert rec["lambda_min"] == 0.0
    assert rec["kappa"] == math.inf and rec["kappa_solve_module"] == math.inf
    assert rec["kappa_effective"] == pytest.approx(rec["lambda_max"] / sorted(np.linalg.eigvalsh(
        (A / np.sqrt(np.outer(A.diagonal(), A.diagonal()))).toarray()))[1], rel=1e-8)
    B = A + sp.identity(n) * 0.5  # definite: the computed numbers are kept
    rec = conditioning._kappa(B)
    assert not rec["singular"] and rec["lambda_min"] > 0 and np.isfinite(rec["kappa_solve_module"])
    assert conditioning._finite_or_inf(3.854926861209539e19) == math.inf
    assert conditioning._finite_or_inf(1551.399209300845) == 1551.399209300845


# --- figures --------------------------------------------------------------------------------------


def _figure(y):
    fig, ax = new_figure(3.0, 2.0)
    ax.loglog([0.2, 0.1, 0.05], y, marker="o", label="error")
    ax.legend()
    return fig


@pytest.mark.parametrize("suffix", [".png", ".pdf", ".svg"])
def test_a_figure_saved_twice_gives_the_same_bytes(tmp_path, suffix):
    """Two saves of one figure (SVG: matplotlib draws a random id salt per file unless one is set)."""
    paths = [save_reproducible(_figure([1.0, 0.3, 0.08]), tmp_path / f"{k}{suffix}") for k in range(2)]
    assert paths[0].read_bytes() == paths[1].read_bytes()


def test_figures_carry_no_date_or_version(tmp_path):
    import matplotlib

    pdf = save_reproducible(_figure([1.0, 0.3, 0.08]), tmp_path / "f.pdf").read_bytes()
    png = save_reproducible(_figure([1.0, 0.3, 0.08]), tmp_path / "f.png").read_bytes()
    svg = save_reproducible(_figure([1.0, 0.3, 0.08]), tmp_path / "f.svg").read_text()
    assert b"/CreationDate" not in pdf and b"/ModDate" not in pdf and b"/Producer" not in pdf
    assert b"Software" not in png and matplotlib.__version__.encode() not in png
    assert "<dc:date>" not in svg and matplotlib.__version__ not in svg
    assert set(FIGURE_METADATA[".pdf"]) >= {"CreationDate", "ModDate", "Producer", "Creator"}


def test_a_figure_of_the_same_numbers_from_two_machines_gives_the_same_bytes(tmp_path):
    """The studies plot the numbers their tables carry (six digits): last-digit differences, which
    move a PDF coordinate written with ten decimals, do not reach the file."""
    a, b = zip(*SAME_NUMBER[:3])
    pa = save_reproducible(_figure(significant(list(a))), tmp_path / "a.pdf")
    pb = save_reproducible(_figure(significant(list(b))), tmp_path / "b.pdf")
    assert pa.read_bytes() == pb.read_bytes()


# --- timing files ---------------------------------------------------------------------------------


def test_the_readme_lists_every_timing_file():
    readme = (ROOT / "README.md").read_text()
    for name in reproduce.TIMING_FILES:
        assert f"paper/{name}" in readme, name
    assert len(reproduce.TIMING_FILES) == 4


@pytest.mark.slow
def test_studies_write_the_same_bytes_on_one_thread_and_on_all(tmp_path):
    """Three studies at the tiny size, once with NUMBA_NUM_THREADS=1 and once with the default
    threads (separate processes: numba reads the variable at import): every tracked output but the
    timing files is byte-identical."""
    outs = []
    for k, threads in enumerate(("1", None)):
        env = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
        if threads is not None:
            env["NUMBA_NUM_THREADS"] = threads
        out = tmp_path / f"run{k}"
        run = subprocess.run([sys.executable, "-m", "cutfem.studies.reproduce", "--tiny", "--quiet", "--out", str(out),
                              "--only", "paper_cut", "conditioning", "other_surfaces"], env=env, capture_output=True, text=True)
        assert run.returncode == 0, run.stderr[-2000:]
        outs.append(out)

    def files(root):
        return {str(p.relative_to(root)) for d in ("figures", "tables") for p in (root / d).rglob("*") if p.is_file()}

    assert files(outs[0]) == files(outs[1])
    compared = sorted(files(outs[0]) - set(reproduce.TIMING_FILES))
    assert len(compared) > 15
    differ = [name for name in compared if (outs[0] / name).read_bytes() != (outs[1] / name).read_bytes()]
    assert differ == [], f"differ between one thread and the default: {differ}"
