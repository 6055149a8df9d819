"""The paper's studies at the tiny size: the files they write, the numbers inside, the claims table,
and that the manuscript only includes files some study writes."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cutfem.studies import paper_cut, paper_meshed, reproduce

PAPER = Path(__file__).resolve().parents[2] / "paper"


def _quiet(message):
    pass


@pytest.fixture(scope="module")
def meshed_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper_meshed")
    summary = paper_meshed.run(out, "tiny", _quiet)
    return out, summary


@pytest.fixture(scope="module")
def cut_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper_cut")
    summary = paper_cut.run(out, "tiny", _quiet)
    return out, summary


def _written(out: Path) -> set:
    return {p.name for p in out.iterdir() if p.is_file()}


def _assert_picture(path: Path, min_ink=0.03):
    """A PNG with something drawn on it: at least ``min_ink`` of the pixels are not white."""
    import matplotlib.image as mpimg

    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] >= 200 and img.shape[1] >= 200
    ink = (img[..., :3] < 0.95).any(axis=2).mean()
    assert ink > min_ink, f"{path.name} is nearly blank ({ink:.3f} of the pixels drawn)"


# ---------------------------------------------------------------------------------------------
# meshed torus
# ---------------------------------------------------------------------------------------------


def test_meshed_writes_exactly_its_outputs(meshed_out):
    out, _ = meshed_out
    assert _written(out) == set(paper_meshed.OUTPUTS)
    for name in paper_meshed.OUTPUTS:
        assert (out / name).stat().st_size > 0
        if name.endswith(".png"):
            _assert_picture(out / name)


def test_meshed_rates_and_invariants(meshed_out):
    out, summary = meshed_out
    data = json.loads((out / "meshed_convergence.json").read_text())
    series = {(s["family"], s["tau_e"]): s for s in data["series"]}
    assert set(series) == {(f, t) for f in ("structured", "flipped", "perturbed", "perturbed-flipped") for t in (0.1, 0.0)}
    assert data["levels"] == [8, 16, 32]
    for fam in ("structured", "flipped", "perturbed", "perturbed-flipped"):
        s = series[(fam, 0.1)]
        # stabilized: errors decrease at every refinement; fitted rate 0.87..0.97 already at n = 8..32
        assert np.all(np.diff(s["discrete_error"]) < 0)
        assert s["rate_fit_discrete"] > 0.8
        assert s["rate_last_discrete"] > 0.9
        # on the finest tiny level the stabilized error is below the unstabilized one
        if fam != "structured":
            assert s["discrete_error"][-1] < 0.35 * series[(fam, 0.0)]["discrete_error"][-1]
    # structured without stabilization: superconvergence (1.92 between n = 16 and 32)
    assert series[("structured", 0.0)]["rate_last_discrete"] > 1.7
    # flipped without stabilization: the error stalls (3.17 -> 2.98 between n = 16 and 32)
    e = series[("flipped", 0.0)]["discrete_error"]
    assert e[-1] > 0.85 * e[-2] and e[-1] > 2.0
    assert series[("flipped", 0.0)]["rate_last_discrete"] < 0.3
    # the integral of H_h over S_h vanishes; the area converges
    for s in data["series"]:
        assert max(s["integral_H_max"]) < 1e-10
        assert np.all(np.diff(s["area_error"]) < 0)
    assert summary["rates_fit_discrete"]["flipped/tau_e=0.1"] == pytest.approx(series[("flipped", 0.1)]["rate_fit_discrete"])


def test_meshed_tables_and_isolines(meshed_out):
    out, _ = meshed_out
    for name in ("meshed_errors_stabilized", "meshed_errors_unstabilized"):
        tex = (out / f"{name}.tex").read_text()
        rows = [line for line in tex.splitlines() if line.endswith("\\\\")]
        assert len(rows) == 1 + 3  # header + n = 8, 16, 32
        assert rows[1].startswith("8 & ")
    rates = (out / "meshed_rates.tex").read_text()
    assert rates.count("\\\\") == 1 + 8
    rows = list(csv.DictReader((out / "meshed_convergence.csv").open()))
    assert len(rows) == 8 * 3
    iso = json.loads((out / "meshed_isolines.json").read_text())
    stab, unstab = iso["range_of_H_h_dot_n"]["0.1"], iso["range_of_H_h_dot_n"]["0.0"]
    # stabilized H_h . n stays near the exact range [0, 8/3]; unstabilized overshoots it widely
    assert -0.5 < stab[0] and stab[1] < 8 / 3 + 0.5
    assert unstab[1] - unstab[0] > 2 * (stab[1] - stab[0])


def test_parameter_triangulation_covers_the_square():
    mesh = paper_meshed.torus_mesh(8, family="flipped", seed=0)
    tp, tri, vertex = paper_meshed.parameter_triangulation(mesh.points, mesh.triangles)
    a, b, c = tp[tri[:, 0]], tp[tri[:, 1]], tp[tri[:, 2]]
    area = 0.5 * np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    # 9 periodic copies of the unrolled torus: total parameter area 9 (2 pi)^2, no fold-overs
    assert area.sum() == pytest.approx(9 * (2 * np.pi) ** 2, rel=1e-12)
    assert np.all(area > 0)
    assert np.array_equal(np.unique(vertex), np.arange(mesh.n_points))


# ---------------------------------------------------------------------------------------------
# cut torus
# ---------------------------------------------------------------------------------------------


def test_cut_writes_exactly_its_outputs(cut_out):
    out, _ = cut_out
    assert _written(out) == set(paper_cut.OUTPUTS)
    for name in paper_cut.OUTPUTS:
        if name.endswith(".png"):
            _assert_picture(out / name)


def test_cut_convergence_numbers(cut_out):
    out, summary = cut_out
    data = json.loads((out / "cut_convergence.json").read_text())
    assert data["spacing"] == [0.4, 0.2, 0.1]
    assert data["box"] == [-1.6, -1.6, -0.6, 1.6, 1.6, 0.6]
    e = np.array(data["l2_error"])
    assert np.all(np.diff(e) < 0)
    assert e[-1] < 0.6  # 0.48 at spacing 0.1
    assert 1.0 < data["rate_fit_l2"] < 1.7  # 1.30 at tiny
    assert np.all(np.diff(data["area_error"]) < 0)
    assert data["rate_fit_area"] > 1.8
    assert max(data["integral_H_max"]) < 1e-10
    assert np.all(np.diff(data["active_tets"]) > 0) and np.all(np.diff(data["dofs"]) > 0)
    # at spacing 0.4 no grid node is on the torus; at 0.1 some are: the zero rule is exercised
    assert data["nodes_on_surface"][0] == 0 and data["nodes_on_surface"][-1] > 0
    tex = (out / "cut_errors.tex").read_text()
    assert tex.count("\\\\") == 1 + 3
    assert summary["rate_fit_l2"] == pytest.approx(data["rate_fit_l2"])


def test_nodes_on_surface_counts_known_points():
    # spacing 0.1: on the plane z = 0 the nodes (±1.5, 0, 0), (0, ±1.5, 0), (±0.5, 0, 0), (0, ±0.5, 0)
    # lie on the torus, and (±1, 0, ±0.5), (0, ±1, ±0.5) on its top and bottom circles
    n = paper_cut.nodes_on_surface(0.1)
    assert n >= 16


# ---------------------------------------------------------------------------------------------
# reproduce: claims, numbers, manuscript
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tables(meshed_out, cut_out, tmp_path_factory):
    tables = tmp_path_factory.mktemp("tables")
    for out in (meshed_out[0], cut_out[0]):
        for p in out.iterdir():
            if p.suffix in (".json", ".tex", ".csv"):
                shutil.copy(p, tables / p.name)
    rows = reproduce._claims_outputs(tables)
    return tables, rows


def test_claims_table(tables):
    tables, rows = tables
    assert (tables / "claims.tex").exists() and (tables / "numbers.tex").exists()
    by_claim = {r["claim"]: r for r in rows}
    assert len(rows) == 13
    assert all(r["agrees"] is True for r in rows if r["kind"] == "integral")
    flipped = next(r for r in rows if "flipped, $\\tau_E = 0$: no" in r["claim"])
    assert flipped["fit"] < 0.6  # 0.34 at tiny: stalls only after n = 16
    cut = next(r for c, r in by_claim.items() if c.startswith("cut, $\\tau_F = 0.1$: $L^2$"))
    assert cut["agrees"] is True and cut["fit"] == pytest.approx(1.30, abs=0.05)
    tex = (tables / "claims.tex").read_text()
    assert tex.count("\\\\") == 1 + len(rows)
    assert json.loads((tables / "claims.json").read_text()) == json.loads(json.dumps(rows))


def _referenced(tex: str):
    body = "\n".join(line.split("%")[0] for line in tex.splitlines())
    graphics = re.findall(r"\\includegraphics(?:\[[^\]]*\])?\{([^}]*)\}", body)
    inputs = re.findall(r"\\input\{([^}]*)\}", body)
    return graphics, inputs


def _declared_stems():
    """Stems of every file a study (or reproduce) declares in OUTPUTS, by folder."""
    stems = set()
    for module in reproduce._load_studies(verbose=False).values():
        for name in getattr(module, "OUTPUTS", []):
            stems.add(Path(name).stem if Path(name).suffix in reproduce.FIGURE_SUFFIXES | reproduce.TABLE_SUFFIXES else name)
    stems |= {Path(n).stem for n in reproduce.OUTPUTS}
    return stems


def test_manuscript_includes_only_generated_files(meshed_out, cut_out):
    graphics, inputs = _referenced((PAPER / "main.tex").read_text())
    assert len(graphics) >= 6 and len(inputs) >= 6
    stems = _declared_stems()
    written = {Path(n).stem for n in _written(meshed_out[0]) | _written(cut_out[0])}
    for ref in graphics:
        folder, name = ref.split("/", 1)
        assert folder == "figures", ref
        assert Path(name).stem in stems, f"{ref} is not written by any study"
        if Path(name).stem.startswith(("meshed_", "cut_")):
            assert Path(name).stem in written, f"{ref} is declared but not written at tiny size"
            assert Path(name).suffix in ("", ".png", ".pdf")
    for ref in inputs:
        folder, name = ref.split("/", 1)
        assert folder == "tables", ref
        assert Path(name).stem in stems, f"{ref} is not written by any study"


def test_manuscript_macros_are_generated(tables):
    tables, _ = tables
    defined = set(re.findall(r"\\newcommand\{\\(\w+)\}", (tables / "numbers.tex").read_text()))
    # reproduce writes the summary macros only when summary.json exists; the study numbers always
    defined |= {"reproduceSize", "reproduceMinutes"}
    tex = (PAPER / "main.tex").read_text()
    own = set(re.findall(r"\\newcommand\{\\(\w+)\}", tex))
    used = set(re.findall(r"\\((?:rate|meshed|cut|claims|reproduce)[A-Za-z]*)", tex))
    missing = used - defined - own
    assert not missing, f"macros used in main.tex but not generated: {sorted(missing)}"


def test_reproduce_cli_errors_and_list(capsys):
    assert reproduce.main(["--list"]) == 0
    listed = capsys.readouterr().out
    assert "paper_meshed" in listed and "paper_cut" in listed
    assert reproduce.main(["--only", "no_such_study", "--quiet"]) == 2


def test_build_script_names_the_packages_without_latex(tmp_path):
    paper = tmp_path / "paper"
    (paper / "tables").mkdir(parents=True)
    (paper / "figures").mkdir()
    (paper / "tables" / "numbers.tex").write_text("")
    shutil.copy(PAPER / "build.sh", paper / "build.sh")
    shutil.copy(PAPER / "main.tex", paper / "main.tex")
    bindir = tmp_path / "bin"
    bindir.mkdir()
    for tool in ("dirname", "tail", "grep"):
        os.symlink(shutil.which(tool), bindir / tool)
    run = subprocess.run([shutil.which("bash"), str(paper / "build.sh")], env={"PATH": str(bindir)}, capture_output=True, text=True)
    assert run.returncode == 3
    assert "texlive-latex-base" in run.stderr and "latexmk" in run.stderr
    # without the generated files it says to run the reproduction first
    (paper / "tables" / "numbers.tex").unlink()
    run = subprocess.run([shutil.which("bash"), str(paper / "build.sh")], env={"PATH": str(bindir)}, capture_output=True, text=True)
    assert run.returncode == 2 and "cutfem reproduce" in run.stderr


@pytest.fixture(scope="module")
def tiny_paper(tmp_path_factory):
    """``cutfem reproduce --tiny`` into a fresh folder: (out, exit status)."""
    out = tmp_path_factory.mktemp("reproduce") / "paper"
    status = reproduce.main(["--tiny", "--out", str(out), "--quiet"])
    return out, status


def test_split_timings_keeps_the_nesting():
    data = {"a": 1, "wall_time": 2.5, "series": [{"x": [1, 2], "seconds": [0.1, 0.2]}, {"x": [3]}], "time": {"solve": 1.0}}
    rest, timings = reproduce.split_timings(data)
    assert rest == {"a": 1, "series": [{"x": [1, 2]}, {"x": [3]}]}
    assert timings == {"wall_time": 2.5, "series": [{"seconds": [0.1, 0.2]}, None], "time": {"solve": 1.0}}
    assert reproduce.split_timings({"a": [1, {"b": 2}]}) == ({"a": [1, {"b": 2}]}, None)


def test_manuscript_includes_figures_at_their_own_size():
    """No \\includegraphics option scales a figure: they are drawn at the printed size."""
    tex = (PAPER / "main.tex").read_text()
    options = re.findall(r"\\includegraphics\[([^\]]*)\]", tex)
    assert options == [], f"figures are scaled in main.tex: {options}"


@pytest.mark.slow
def test_reproduce_tiny_and_build(tiny_paper):
    """The whole chain at the tiny size: every available study, the claims, figures at the printed
    width, timings kept apart, and (with LaTeX) the PDF."""
    out, status = tiny_paper
    summary = json.loads((out / "tables" / "summary.json").read_text())
    assert status == 0, {k: v.get("error") for k, v in summary["studies"].items() if v["status"] != "ok"}
    assert set(summary["studies"]) == set(reproduce._load_studies(verbose=False))
    timings = json.loads((out / "tables" / "timings.json").read_text())
    assert set(timings["studies"]) == set(summary["studies"])
    assert all(v["wall_time"] > 0 for v in timings["studies"].values())
    assert timings["total_wall_time"] >= max(v["wall_time"] for v in timings["studies"].values())
    # no table but the timing files holds a wall time
    for path in (out / "tables").glob("*.json"):
        if f"tables/{path.name}" not in reproduce.TIMING_FILES:
            assert reproduce.split_timings(json.loads(path.read_text()))[1] is None, path.name
    for path in (out / "tables").glob("*.csv"):
        header = path.read_text().splitlines()[0].split(",")
        assert not set(header) & reproduce.TIMING_KEYS, path.name
    # every figure is drawn at most 6.3 in (the text width) wide: it prints at scale 1
    for path in (out / "figures").glob("*.pdf"):
        box = re.search(rb"/MediaBox \[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", path.read_bytes())
        assert box is not None and float(box.group(1)) <= 6.3 * 72 + 0.5, (path.name, box and box.group(1))
    for name in paper_meshed.OUTPUTS + paper_cut.OUTPUTS:
        folder = "figures" if Path(name).suffix in (".png", ".pdf") else "tables"
        assert (out / folder / name).exists(), name
    graphics, inputs = _referenced((PAPER / "main.tex").read_text())
    for ref in graphics:
        assert any((out / (ref + ext)).exists() for ext in ("", ".pdf", ".png")), ref
    for ref in inputs:
        assert (out / (ref + ".tex")).exists(), ref
    if shutil.which("pdflatex") is None:
        pytest.skip("pdflatex is not installed: the PDF build is not checked")
    shutil.copy(PAPER / "main.tex", out / "main.tex")
    shutil.copy(PAPER / "build.sh", out / "build.sh")
    run = subprocess.run(["bash", str(out / "build.sh")], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert (out / "main.pdf").stat().st_size > 100_000


@pytest.mark.slow
def test_reproduce_twice_gives_identical_files(tiny_paper, tmp_path):
    """A second run changes no byte of the tracked outputs (figures/, tables/) except the files that
    hold timings; data/ (raw per-level records, not tracked) is not compared."""
    first, _ = tiny_paper
    second = tmp_path / "paper"
    assert reproduce.main(["--tiny", "--out", str(second), "--quiet"]) == 0

    def files(root):
        return {str(p.relative_to(root)) for d in ("figures", "tables") for p in (root / d).rglob("*") if p.is_file()}

    assert files(first) == files(second)
    compared = sorted(files(first) - set(reproduce.TIMING_FILES))
    assert len(compared) > 40
    differ = [name for name in compared if (first / name).read_bytes() != (second / name).read_bytes()]
    assert differ == [], f"changed between two identical runs: {differ}"
