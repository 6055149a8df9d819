"""Every figure and table of the paper: ``cutfem reproduce [--out DIR] [--tiny | --quick | --full] [--only NAME ...]``.

Runs the study modules listed in :data:`STUDY_NAMES` that exist (a missing module is skipped with a
note), each into a scratch folder, then files their outputs: figures (PNG, PDF) into ``OUT/figures``,
tables and numbers (TeX, JSON, CSV) into ``OUT/tables``, anything else into ``OUT/data/NAME``.  Then
it compares the measured rates with the published claims (``OUT/tables/claims.tex`` and
``claims.json``), writes LaTeX macros with the key numbers (``OUT/tables/numbers.tex``) for the
manuscript, and a summary of the run (``OUT/tables/summary.json``).

Wall times differ on every run, so they are kept apart: the entries named in :data:`TIMING_KEYS` are
taken out of every JSON and CSV table a study writes and, with the wall time of every study, go to
``OUT/tables/timings.json`` (and the total, as a LaTeX macro, to ``OUT/tables/timings.tex``).  The
other outputs are the same bytes on every machine and thread count: JSON and CSV with six
significant digits (sums in another order change the 14th), round-off quantities written as their
bound (:func:`cutfem.studies.common.roundoff_zero`), figures drawn from those digits and saved
without dates, so that a rerun changes no file but those of :data:`TIMING_FILES` (listed in the
README).
Progress goes to standard error.  Default ``OUT`` is ``paper`` (the manuscript's folder), default
size ``quick`` (a few minutes on 2 cores); ``--full`` runs the paper's finest levels.

The exit status is 0 when every selected study ran, 1 otherwise (the others still run).
"""

from __future__ import annotations

import argparse
import csv
import importlib
import json
import shutil
import sys
import time
import traceback
from pathlib import Path

import numpy as np

from cutfem.runs.registry import ProblemError
from cutfem.runs.runner import check_output, compile_notice

from .common import ROUNDOFF_INTEGRAL, Progress, fmt_roundoff, save_json

#: the studies, in the order they run (the paper's own experiments first)
STUDY_NAMES = [
    "paper_meshed",
    "paper_cut",
    "conditioning",
    "stabilization_sweeps",
    "curvature_baselines",
    "laplace_beltrami",
    "other_surfaces",
    "two_phase",
    "higher_order",
]

FIGURE_SUFFIXES = {".png", ".pdf", ".svg", ".jpg", ".jpeg"}
TABLE_SUFFIXES = {".tex", ".json", ".csv", ".txt"}

#: files written by reproduce itself (into OUT/tables)
OUTPUTS = ["claims.tex", "claims.json", "numbers.tex", "summary.json", "timings.json", "timings.tex"]

#: keys (JSON) and columns (CSV) of the study tables that hold wall times
TIMING_KEYS = frozenset({"wall_time", "time", "seconds", "this_run_wall_time", "total_wall_time"})

#: outputs (relative to OUT) that hold timings and so change on every run
TIMING_FILES = (
    "tables/timings.json",
    "tables/timings.tex",
    "figures/curvature_baselines_time.png",
    "figures/curvature_baselines_time.pdf",
)


def _load_studies(names=STUDY_NAMES, verbose=True):
    found = {}
    for name in names:
        try:
            found[name] = importlib.import_module(f"cutfem.studies.{name}")
        except ImportError as exc:
            if verbose:
                print(f"note: study {name!r} is not available ({exc}); skipped", file=sys.stderr)
    return found


STUDIES = _load_studies(verbose=False)


# ---------------------------------------------------------------------------------------------
# claims of the paper against the measured rates
# ---------------------------------------------------------------------------------------------

#: (tolerance) rules deciding "agrees"
AT_LEAST_ONE = 0.9  # "rate at least 1": the fitted rate is >= 0.9
ABOUT_TOL = 0.25  # "about r": |fitted - r| <= 0.25
NO_CONVERGENCE = 0.25  # "no convergence": fitted rate <= 0.25
ZERO_INTEGRAL = 1e-8  # the integral of H_h: every component below 1e-8 in modulus


def _read(tables: Path, name: str):
    path = tables / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


#: the study tables the claims and the manuscript's numbers are taken from: (study, its subject)
CLAIM_TABLES = {"meshed_convergence": ("paper_meshed", "meshed torus"), "cut_convergence": ("paper_cut", "cut torus")}


def _study_status(tables: Path, name: str):
    """The status of the study that writes table ``name`` in the run recorded in ``summary.json``:
    None when it ran ("ok") or when there is no summary (the tables alone), else "failed" or
    "did not run".  A study that failed or did not run may have left the JSON of an earlier run."""
    summary = _read(tables, "summary")
    if summary is None:
        return None
    entry = summary.get("studies", {}).get(CLAIM_TABLES[name][0])
    status = "did not run" if entry is None else entry.get("status")
    return None if status == "ok" else status


def _read_current(tables: Path, name: str):
    """Table ``name`` when the study that writes it ran in the last run, else None."""
    return None if _study_status(tables, name) is not None else _read(tables, name)


def _r(x):
    return "--" if x is None or not np.isfinite(x) else f"{x:.2f}"


def _num(x) -> float:
    """A number of a study table as a float: NaN for null (the studies save NaN and infinities as
    null), so that every comparison with it is False and a missing number never agrees."""
    return float("nan") if x is None else float(x)


def _worst(values) -> float:
    """The largest of ``values``; NaN when any is NaN or null (np.max, unlike max, propagates it)."""
    return float(np.max([_num(v) for v in values]))


def claims(tables: Path) -> list[dict]:
    """The published claims (docs/math.md §3) next to the rates measured by paper_meshed and paper_cut.

    Each row: claim, the paper's value, measured (least-squares fit over all levels, and the rate
    between the two finest levels), the criterion and whether it is met (True/False, None when the
    paper states nothing)."""
    rows = []
    meshed = _read_current(tables, "meshed_convergence")
    cut = _read_current(tables, "cut_convergence")

    def row(claim, paper, fit, last, criterion, agrees, source, kind="rate"):
        rows.append({"claim": claim, "paper": paper, "fit": fit, "last": last, "criterion": criterion, "agrees": agrees, "source": source, "kind": kind})

    for name, (study, subject) in CLAIM_TABLES.items():
        status = _study_status(tables, name)
        if status is not None:  # its claims cannot be checked: one row that disagrees says so
            row(f"{subject}: no numbers from the last run", "--", None, None, "the study ran", False, f"{study} {status}", kind="study")

    if meshed is not None:
        series = {(s["family"], s["tau_e"]): s for s in meshed["series"]}
        lv = meshed["levels"]
        src = f"meshed torus, n = {lv[0]}..{lv[-1]}"
        series = {k: {**s, "rate_fit_discrete": _num(s["rate_fit_discrete"])} for k, s in series.items()}
        for fam in ("structured", "flipped", "perturbed", "perturbed-flipped"):
            s = series.get((fam, 0.1))
            if s is None:
                continue
            paper = "$\\ge 1$" if fam != "perturbed-flipped" else "not in paper; theory $\\ge 1$"
            row(f"meshed, {fam}, $\\tau_E = 0.1$: $O(h)$", paper, s["rate_fit_discrete"], s["rate_last_discrete"],
                f"fit $\\ge {AT_LEAST_ONE}$", s["rate_fit_discrete"] >= AT_LEAST_ONE, src)
        s = series.get(("structured", 0.0))
        if s is not None:
            row("meshed, structured, $\\tau_E = 0$: superconvergence", "$\\approx 2$", s["rate_fit_discrete"], s["rate_last_discrete"],
                f"$|\\text{{fit}} - 2| \\le {ABOUT_TOL}$", abs(s["rate_fit_discrete"] - 2) <= ABOUT_TOL, src)
        s = series.get(("flipped", 0.0))
        if s is not None:
            row("meshed, flipped, $\\tau_E = 0$: no convergence", "none", s["rate_fit_discrete"], s["rate_last_discrete"],
                f"fit $\\le {NO_CONVERGENCE}$", s["rate_fit_discrete"] <= NO_CONVERGENCE, src)
        for fam in ("perturbed", "perturbed-flipped"):
            s = series.get((fam, 0.0))
            if s is not None:
                row(f"meshed, {fam}, $\\tau_E = 0$", "not stated", s["rate_fit_discrete"], s["rate_last_discrete"], "--", None, src)
        worst = _worst([v for s in meshed["series"] for v in s["integral_H_max"]])
        row("meshed: $\\int_{S_h} H_h = 0$", "exact", worst, None, "$\\max |\\cdot| \\le 10^{-8}$", worst <= ZERO_INTEGRAL, src, kind="integral")
    if cut is not None:
        sp = cut["spacing"]
        cut = {**cut, "rate_fit_l2": _num(cut["rate_fit_l2"]), "rate_fit_area": _num(cut["rate_fit_area"])}
        src = f"cut torus, spacing {sp[0]:g}..{sp[-1]:g}"
        row("cut, $\\tau_F = 0.1$: $L^2$ rate", "$\\approx 1.3$", cut["rate_fit_l2"], cut["rate_last_l2"],
            f"$|\\text{{fit}} - 1.3| \\le {ABOUT_TOL}$", abs(cut["rate_fit_l2"] - 1.3) <= ABOUT_TOL, src)
        row("cut, $\\tau_F = 0.1$: $O(h)$ (theory)", "$\\ge 1$", cut["rate_fit_l2"], cut["rate_last_l2"],
            f"fit $\\ge {AT_LEAST_ONE}$", cut["rate_fit_l2"] >= AT_LEAST_ONE, src)
        row("cut: area of $S_h$, $O(h^2)$", "$2$", cut["rate_fit_area"], cut["rate_last_area"],
            f"$|\\text{{fit}} - 2| \\le {ABOUT_TOL}$", abs(cut["rate_fit_area"] - 2) <= ABOUT_TOL, src)
        worst = _worst(cut["integral_H_max"])
        row("cut: $\\int_{S_h} H_h = 0$", "exact", worst, None, "$\\max |\\cdot| \\le 10^{-8}$", worst <= ZERO_INTEGRAL, src, kind="integral")
    return rows


def _plain(tex: str) -> str:
    """A LaTeX snippet of the claims table as terminal text."""
    for a, b in (("$", ""), ("\\tau", "tau"), ("\\ge", ">="), ("\\le", "<="), ("\\approx", "~"), ("\\int_{S_h} H_h", "int H_h"), ("\\text", ""), ("{", ""), ("}", ""), ("\\", "")):
        tex = tex.replace(a, b)
    return tex


def _claims_outputs(tables: Path) -> list[dict]:
    rows = claims(tables)
    save_json(tables, "claims", rows)
    lines = [
        "\\begin{tabular}{llrrll}",
        "\\hline",
        "claim & paper & measured (fit) & last pair & criterion & agrees \\\\",
        "\\hline",
    ]
    for r in rows:
        integral = r["kind"] == "integral"
        fit = "--" if r["fit"] is None else (fmt_roundoff(r["fit"]) if integral else _r(r["fit"]))
        agrees = "n/a" if r["agrees"] is None else ("yes" if r["agrees"] else "\\textbf{no}")
        lines.append(f"{r['claim']} & {r['paper']} & {fit} & {_r(r['last'])} & {r['criterion']} & {agrees} \\\\")
    lines += ["\\hline", "\\end{tabular}"]
    (tables / "claims.tex").write_text("\n".join(lines) + "\n")
    _numbers(tables, rows)
    return rows


def _numbers(tables: Path, rows):
    """LaTeX macros with the measured numbers, for the manuscript's prose (\\input{tables/numbers})."""
    meshed = _read_current(tables, "meshed_convergence")
    cut = _read_current(tables, "cut_convergence")
    summary = _read(tables, "summary")
    macros = {}
    names = {"structured": "Structured", "flipped": "Flipped", "perturbed": "Perturbed", "perturbed-flipped": "PerturbedFlipped"}
    if meshed is not None:
        for s in meshed["series"]:
            tag = names[s["family"]] + ("Stab" if s["tau_e"] > 0 else "Unstab")
            macros[f"rate{tag}"] = _r(s["rate_fit_discrete"])
            macros[f"rateLast{tag}"] = _r(s["rate_last_discrete"])
        stab = [s for s in meshed["series"] if s["tau_e"] > 0]
        for key, tag in (("rate_fit_discrete", "Fit"), ("rate_last_discrete", "Last")):
            values = [_num(s[key]) for s in stab]
            macros[f"meshedStab{tag}Min"] = _r(np.min(values))
            macros[f"meshedStab{tag}Max"] = _r(np.max(values))
        macros["meshedNmin"] = str(meshed["levels"][0])
        macros["meshedNmax"] = str(meshed["levels"][-1])
    isolines = _read(tables, "meshed_isolines")
    if isolines is not None:
        macros["isolinesN"] = str(isolines["n"])
    if cut is not None:
        macros["rateCut"] = _r(cut["rate_fit_l2"])
        macros["rateLastCut"] = _r(cut["rate_last_l2"])
        macros["rateCutArea"] = _r(cut["rate_fit_area"])
        macros["cutPairRates"] = ", ".join(_r(x) for x in cut["rates_l2"])
        macros["cutSpacingMin"] = f"{cut['spacing'][-1]:g}"
        macros["cutSpacingMax"] = f"{cut['spacing'][0]:g}"
        macros["cutDofsMax"] = str(cut["dofs"][-1])
        macros["cutNodesOnSurface"] = str(max(cut["nodes_on_surface"]))
        worst = _worst(cut["integral_H_max"])
        # below ROUNDOFF_INTEGRAL the integral is round-off (saved as 0): its bound is the number
        bound = max(worst, ROUNDOFF_INTEGRAL)
        macros["cutIntegralMax"] = "--" if not np.isfinite(worst) else f"$10^{{{int(np.ceil(np.log10(bound)))}}}$"
    agree = [r for r in rows if r["agrees"] is not None]
    macros["claimsAgree"] = str(sum(bool(r["agrees"]) for r in agree))
    macros["claimsTotal"] = str(len(agree))
    if summary is not None:
        # with --only, the tables may come from runs of different sizes: name each size once
        sizes = [e.get("size") for e in summary.get("studies", {}).values() if e.get("size")] or [summary.get("size", "?")]
        macros["reproduceSize"] = " + ".join(sorted(set(sizes), key=("tiny", "quick", "full", *sizes).index))
    text = "% generated by studies/reproduce.py from the study JSON files; do not edit\n"
    text += "".join(f"\\newcommand{{\\{k}}}{{{v}}}\n" for k, v in macros.items())
    (tables / "numbers.tex").write_text(text)


# ---------------------------------------------------------------------------------------------
# timings, kept apart from the numbers
# ---------------------------------------------------------------------------------------------


def split_timings(data):
    """``(rest, timings)``: ``data`` (nested dicts and lists) without the entries whose key is in
    :data:`TIMING_KEYS`, and those entries in the same nesting (None where a part has none)."""
    if isinstance(data, dict):
        rest, timings = {}, {}
        for k, v in data.items():
            if k in TIMING_KEYS:
                timings[k] = v
            else:
                rest[k], t = split_timings(v)
                if t is not None:
                    timings[k] = t
        return rest, (timings or None)
    if isinstance(data, list):
        parts = [split_timings(v) for v in data]
        timings = [t for _, t in parts]
        return [r for r, _ in parts], (timings if any(t is not None for t in timings) else None)
    return data, None


def _move_timings(out: Path, files: list[str]) -> dict:
    """Take the timings out of the JSON and CSV tables among ``files`` (paths relative to
    ``out``), rewriting them; returns ``{file: timings}``."""
    moved = {}
    for key in files:
        path = out / key
        if not key.startswith("tables/") or key in TIMING_FILES:
            continue
        if path.suffix == ".json":
            rest, timings = split_timings(json.loads(path.read_text()))
            save_json(path.parent, path.stem, rest)
        elif path.suffix == ".csv":
            with path.open(newline="") as fh:
                rows = list(csv.DictReader(fh))
            columns = list(rows[0]) if rows else []
            gone = [c for c in columns if c in TIMING_KEYS]
            if not gone:
                continue
            timings = {c: [r[c] for r in rows] for c in gone}
            with path.open("w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=[c for c in columns if c not in TIMING_KEYS])
                w.writeheader()
                w.writerows({c: v for c, v in r.items() if c not in TIMING_KEYS} for r in rows)
        else:
            continue
        if timings is not None:
            moved[key] = timings
    return moved


def _timings_outputs(tables: Path, timings: dict) -> None:
    save_json(tables, "timings", timings)
    text = "% generated by studies/reproduce.py: wall times of the last run (change on every run)\n"
    text += f"\\newcommand{{\\reproduceMinutes}}{{{timings.get('total_wall_time', 0.0) / 60:.1f}}}\n"
    (tables / "timings.tex").write_text(text)


# ---------------------------------------------------------------------------------------------
# running
# ---------------------------------------------------------------------------------------------


def _file_outputs(scratch: Path, out: Path, name: str, owners: dict) -> list[str]:
    moved = []
    for path in sorted(scratch.rglob("*")):
        if not path.is_file():
            continue
        rel = path.relative_to(scratch)
        suffix = path.suffix.lower()
        if len(rel.parts) == 1 and suffix in FIGURE_SUFFIXES:
            dest = out / "figures" / rel
        elif len(rel.parts) == 1 and suffix in TABLE_SUFFIXES:
            dest = out / "tables" / rel
        else:
            dest = out / "data" / name / rel
        if dest.name in OUTPUTS and dest.parent.name == "tables":
            dest = out / "data" / name / rel
        key = str(dest.relative_to(out))
        if key in owners and owners[key] != name:
            print(f"warning: {key} is written by both {owners[key]} and {name}; {name}'s copy wins", file=sys.stderr)
        owners[key] = name
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(path), dest)
        moved.append(key)
    return moved


def main(argv=None) -> int:
    from cutfem.memory import configure

    configure()  # a large run: opt into the allocation settings (cutfem.memory)
    p = argparse.ArgumentParser(prog="cutfem reproduce", description="run every study of the paper; figures to OUT/figures, tables to OUT/tables")
    p.add_argument("--out", default="paper", help="output folder (default: paper in the current folder: the manuscript's folder when run from the repository)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--tiny", dest="size", action="store_const", const="tiny", help="seconds; for tests")
    g.add_argument("--quick", dest="size", action="store_const", const="quick", help="the default: a few minutes")
    g.add_argument("--full", dest="size", action="store_const", const="full", help="the paper's finest levels (long; several GB of memory)")
    p.add_argument("--only", nargs="+", metavar="NAME", default=None, help=f"run only these studies (of: {', '.join(STUDY_NAMES)})")
    p.add_argument("--list", action="store_true", help="list the studies and exit")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    a = p.parse_args(argv)
    size = a.size or "quick"
    studies = _load_studies(verbose=not a.quiet)
    if a.list:
        for name in STUDY_NAMES:
            print(f"{name:24s} {'available' if name in studies else 'missing'}")
        return 0
    selected = list(studies)
    if a.only:
        unknown = [n for n in a.only if n not in STUDY_NAMES]
        if unknown:
            print(f"error: unknown study {', '.join(unknown)}; studies: {', '.join(STUDY_NAMES)}", file=sys.stderr)
            return 2
        missing = [n for n in a.only if n not in studies]
        if missing:
            print(f"error: study {', '.join(missing)} is not available (module missing)", file=sys.stderr)
            return 2
        selected = [n for n in STUDY_NAMES if n in a.only]

    try:
        check_output("--out", a.out, folder=True)
    except ProblemError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(a.out)
    tables = out / "tables"
    for d in (out / "figures", tables):
        d.mkdir(parents=True, exist_ok=True)
    previous = _read(tables, "summary") or {}
    previous_timings = _read(tables, "timings") or {}
    summary = {"size": size, "studies": dict(previous.get("studies", {})) if a.only else {}}
    timings = {"studies": dict(previous_timings.get("studies", {})) if a.only else {},
               "files": dict(previous_timings.get("files", {})) if a.only else {}}
    owners: dict = {}
    t_all = time.perf_counter()
    failed = []
    for k, name in enumerate(selected):
        progress = Progress(name, not a.quiet)
        progress(f"=== study {k + 1}/{len(selected)}: {name} ({size}) ===")
        scratch = out / ".scratch" / name
        if scratch.exists():
            shutil.rmtree(scratch)
        scratch.mkdir(parents=True)
        t0 = time.perf_counter()
        entry = {"size": size}
        try:
            with compile_notice(progress):  # Progress says nothing when quiet
                result = studies[name].run(scratch, size, progress)
            entry.update(status="ok", result=result)
        except Exception as exc:  # one broken study must not stop the others
            entry.update(status="failed", error=f"{type(exc).__name__}: {exc}")
            failed.append(name)
            print(f"[{name}] FAILED: {type(exc).__name__}: {exc}", file=sys.stderr)
            traceback.print_exc(file=sys.stderr)
        wall_time = time.perf_counter() - t0
        entry["files"] = _file_outputs(scratch, out, name, owners)
        shutil.rmtree(scratch, ignore_errors=True)
        timings["files"].update(_move_timings(out, entry["files"]))
        entry["result"], result_timings = split_timings(entry.get("result"))
        timings["studies"][name] = {"wall_time": wall_time, **({"result": result_timings} if result_timings else {})}
        summary["studies"][name] = entry
        progress(f"{entry['status']} in {wall_time:.1f} s, {len(entry['files'])} files")
    shutil.rmtree(out / ".scratch", ignore_errors=True)
    timings["this_run_wall_time"] = time.perf_counter() - t_all
    # with --only, the entries of earlier runs are kept: the total is over every study listed
    timings["total_wall_time"] = sum(v.get("wall_time", 0.0) for v in timings["studies"].values())
    summary["missing_studies"] = [n for n in STUDY_NAMES if n not in studies]
    save_json(tables, "summary", summary)
    _timings_outputs(tables, timings)
    rows = _claims_outputs(tables)
    if not a.quiet:
        print(f"\nreproduce ({size}): {len(selected) - len(failed)}/{len(selected)} studies ok in {timings['this_run_wall_time']:.1f} s; "
              f"figures in {out / 'figures'}, tables in {tables}", file=sys.stderr)
        for r in rows:
            agrees = "n/a" if r["agrees"] is None else ("yes" if r["agrees"] else "NO")
            fit = "--" if r["fit"] is None else _plain(fmt_roundoff(r["fit"])) if r["kind"] == "integral" else f"{float(r['fit']):.3g}"
            print(f"  {_plain(r['claim']):<52s} paper {_plain(r['paper']):<18s} measured {fit:<9} agrees {agrees}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
