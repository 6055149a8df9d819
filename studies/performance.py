"""Performance benchmark: stage times, peak memory and sizes of the mean curvature problems, with a
lower bound for every stage, the fitted exponents, the commands of the targets timed end to end,
ngsxfem beside it, bulk Poisson, and the largest level that fits in memory.

The cut torus of docs/math.md §6 at spacings 0.1 ... 0.0125 (down to 0.003125 with ``--full``),
and the meshed torus (flipped and perturbed families) at n = 64 ... 768.  How a level is measured
(a fresh process for each, the stages, the second run in its process, CPU times, page faults and
the peak) is :mod:`cutfem.studies.performance_levels`; what the stages are held against (the
memory-traffic bounds, the compiled references and the per-stage targets) is
:mod:`cutfem.studies.performance_bounds`.  Each level runs three times (once at the tiny size)
and the fastest run is kept, with all the totals recorded (``totals``).

Options of the command line (besides ``--out`` and the size flags)
------------------------------------------------------------------
* ``--peers``: the same cut torus level in ngsxfem
  (:func:`cutfem.studies.peers_ngsxfem.ngsxfem_mean_curvature` on the same Kuhn tets, the same
  snapped level set, zeros to +1e-14 and the collapsed tets left out, so the same unknowns;
  NGSolve's sparse Cholesky, one thread), once per level in a fresh process, down to
  ``--peers-down-to`` (0.025: the NGSolve mesh of the whole background needs about 400 bytes a
  background tet, 15 GB at 0.0125) and only where that fits in ``--memory-gib`` and in 90 % of
  the available memory; the ratio ngsxfem / cutfem of the stage sums (``ratio``).  cutfem keeps
  its automatic solver (CG with multigrid above :data:`cutfem.solvers.solve.DIRECT_LIMIT`
  unknowns).  Without ngsolve/xfem a note is printed and saved (``peers.skipped``).
* ``--limit``: the cut torus at spacings 0.1, 0.05, ... (one run each, fresh processes, no second
  run in the process: a level near the memory limit runs once) until the
  next level's predicted peak exceeds ``--memory-gib`` (default 20) or 90 % of the memory
  available when it would start (:func:`limit_search`); records the largest level that ran and the
  prediction for the next (:func:`predict_next`: the fitted exponents, memory at least linear in the
  active tets).  The meshed levels are not run in this mode.
* ``--bulk``: fictitious-domain Poisson on the solid torus, ``cutfem run poisson-cut --surface torus
  --spacing S --json F`` in a fresh process per level (0.1, 0.05, 0.025; with ``--full`` also
  0.0125 and 0.01, 2.7 and 5.2 million unknowns, about 7.5 GiB at the finest; one run each):
  unknowns, wall time, stages, peak memory, time and memory per million unknowns.

End to end through the command line (``commands``; not in ``--limit`` mode): the commands of the
targets (:func:`~cutfem.studies.performance_levels.command_targets`:
``cutfem run mean-curvature-cut --spacing 0.0125``, target 2 s;
``cutfem run mean-curvature-meshed --levels 768 --family F`` for the four families, target 1 s;
with ``--full`` also ``--spacing 0.003125``, target 40 s), each run as many times as the levels
in fresh processes, the runs of the commands interleaved; the wall time of the whole process
(interpreter start, imports and numba's start included, as from the shell), the median and range
of the runs, the peak, and whether the median meets the target.  The package is compiled to
bytecode first (:func:`~cutfem.studies.performance_levels.compile_bytecode`).

Exponents (``exponents``): least-squares slopes of log(wall time), log(user CPU time),
log(peak memory) and log(stage time) against log(active tets) over the three finest cut levels
that ran (none with fewer than three), and of log(wall time) and log(peak) against log(unknowns)
for the bulk levels; with more than three cut levels at spacing :data:`EXPONENT_FROM` and finer
(``--full``), also the slopes over all of them (``cut from 0.025``).  The figure
``performance_scaling`` shows time and memory against active tets (cut, with ngsxfem when run) or
surface nodes (meshed) on log-log axes with the exponents;
``performance_bounds`` shows measured / bound per stage and level, the per-stage verdict of
``stage_targets`` (both ratios of each stage against the target 2) and, with ``--bulk``, the bulk
costs per million unknowns.
"""

from __future__ import annotations

import contextlib
import io
import sys
from pathlib import Path

import numpy as np

from cutfem.geometry.box import structured_box
from cutfem.runs.convergence import new_figure

from .common import PAGE_WIDTH, Progress, figure_style, pick, save_figure, save_json, study_main
from .peers_ngsxfem import BYTES_PER_TET, INSTALL, available_memory, peer_missing
from .performance_bounds import bandwidth_in_fresh_process, references_in_fresh_process, stage_bounds, stage_targets
from .performance_levels import BOX, CUT_STAGES, bulk_level, command_times, compile_bytecode, level_in_fresh_process

OUTPUTS = ["performance", "performance_scaling", "performance_bounds"]

#: the coarsest cut level of the second fit of the exponents (the range of the scaling target)
EXPONENT_FROM = 0.025

#: ngsxfem runs at spacings >= this by default (the NGSolve mesh covers the whole background)
PEERS_DOWN_TO = 0.025
#: the cut levels of --limit start here and halve
LIMIT_START = 0.1
#: the bulk levels of --full (poisson-cut on the solid torus): 0.01 has 5.2 million unknowns
BULK_FULL = [0.1, 0.05, 0.025, 0.0125, 0.01]


def fitted_exponent(x, y) -> float:
    """Least-squares slope of log y against log x."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    return float(np.polyfit(np.log(x), np.log(y), 1)[0]) if len(x) >= 2 else float("nan")


# ---------------------------------------------------------------------------------------------
# exponents
# ---------------------------------------------------------------------------------------------


def scaling_exponents(records: list[dict], x: str = "active_tets", finest: int = 3, stages=(), time_key: str = "total") -> dict:
    """Slopes of log(``time_key``), log(cpu_user), log(peak_memory_gib) and log(time[stage]) for each of
    ``stages`` against log(``x``) over the ``finest`` records with the largest ``x`` (keys absent
    from the records are skipped).  Empty dict with fewer than ``finest`` records: an exponent
    fitted to two coarse levels says more about start-up costs than about scaling."""
    rs = sorted(records, key=lambda r: r[x])[-finest:]
    if len(rs) < finest:
        return {}
    xs = [r[x] for r in rs]
    out = {"levels": [r["level"] for r in rs], "x": x}
    for key, name in ((time_key, "time"), ("cpu_user", "user_time"), ("peak_memory_gib", "memory")):
        if all(key in r for r in rs):
            out[name] = fitted_exponent(xs, [r[key] for r in rs])
    times = {s: [r["time"].get(s, 0.0) for r in rs] for s in stages}
    out["stages"] = {s: fitted_exponent(xs, v) for s, v in times.items() if min(v) > 0}
    return out


# ---------------------------------------------------------------------------------------------
# the largest level that fits
# ---------------------------------------------------------------------------------------------


def predict_next(levels: list[dict], spacing: float) -> dict:
    """The active tets and peak memory of the cut level at ``spacing`` from the ``levels`` already
    run (records with ``level``, ``active_tets``, ``peak_memory_gib``): with q the slope of
    log(active tets) against log(spacing) and p that of log(peak) against log(active tets), both
    over the last three levels, T = T_last (spacing / s_last)^q and peak = peak_last (T / T_last)^P
    with P = max(p, 1): every array of a level grows at least like its active tets, and a fitted
    p below 1 comes from the fixed memory of the interpreter and its imports (0.12 GiB), which
    weighs less and less (measured: p = 0.32 over spacings 0.1-0.025 predicted 0.48 GiB at 0.0125,
    which took 1.02 GiB; P = 1 predicts 1.27 GiB).  With a single level, q = -2 (a surface band)
    and p = 1 are assumed."""
    last = levels[-3:]
    if len(last) >= 2:
        q = fitted_exponent([r["level"] for r in last], [r["active_tets"] for r in last])
        p = fitted_exponent([r["active_tets"] for r in last], [r["peak_memory_gib"] for r in last])
        how = f"fitted over spacings {[r['level'] for r in last]}"
    else:
        q, p, how = -2.0, 1.0, "assumed (one level): tets ~ spacing^-2, peak ~ tets"
    r = levels[-1]
    tets = r["active_tets"] * (spacing / r["level"]) ** q
    used = max(p, 1.0)
    return {"spacing": spacing, "active_tets": tets, "peak_memory_gib": r["peak_memory_gib"] * (tets / r["active_tets"]) ** used,
            "tets_exponent": q, "memory_exponent": p, "memory_exponent_used": used, "exponents": how}


def limit_search(runner, memory_gib: float, start: float = LIMIT_START, available_gib=None, progress=None,
                 max_levels: int = 16) -> dict:
    """Run cut levels at ``start``, start/2, ... with ``runner(spacing) -> record`` (a record with
    ``active_tets`` and ``peak_memory_gib``, or ``failed``) until the next level's predicted peak
    (:func:`predict_next`) exceeds ``memory_gib`` or 90 % of ``available_gib()`` (GiB available
    now; None: no such check), a level fails, or a level's measured peak exceeds the limit.

    Returns {"memory_gib", "levels" (the records run), "largest" (the finest level that ran
    within the limit, None if none did), "next" (the prediction for the level after it),
    "stopped" (why)}."""
    if not memory_gib > 0:
        raise ValueError(f"--memory-gib must be a positive number of GiB, got {memory_gib!r}")
    say = progress or (lambda msg: None)
    levels, spacing, stopped = [], float(start), None
    for _ in range(max_levels):
        if levels:
            pred = predict_next(levels, spacing)
            avail = available_gib() if available_gib else None
            cap = memory_gib if avail is None else min(memory_gib, 0.9 * avail)
            if pred["peak_memory_gib"] > cap:
                which = "the limit" if cap == memory_gib else f"90 % of the available {avail:.1f} GiB"
                stopped = f"spacing {spacing:g} predicted to need {pred['peak_memory_gib']:.2f} GiB > {cap:.2f} GiB ({which})"
                break
            say(f"limit: spacing {spacing:g}, predicted {pred['peak_memory_gib']:.2f} GiB")
        rec = runner(spacing)
        levels.append(rec)
        if "failed" in rec:
            stopped = f"spacing {spacing:g} failed"
            break
        if rec["peak_memory_gib"] > memory_gib:
            stopped = f"spacing {spacing:g} used {rec['peak_memory_gib']:.2f} GiB > {memory_gib:g} GiB"
            break
        spacing /= 2
    else:
        stopped = f"{max_levels} levels run"
    ran = [r for r in levels if "failed" not in r and r["peak_memory_gib"] <= memory_gib]
    largest = ran[-1] if ran else None
    nxt = predict_next(ran, largest["level"] / 2) if largest else None
    return {"memory_gib": memory_gib, "levels": levels, "stopped": stopped, "next": nxt,
            "largest": None if largest is None else {k: largest[k] for k in ("level", "active_tets", "dofs", "peak_memory_gib", "total") if k in largest}}


def _available_gib():
    avail = available_memory()
    return None if avail is None else avail / 2**30


def _peer_missing():
    with contextlib.redirect_stdout(io.StringIO()):  # xfem prints its version when imported
        why = peer_missing()
    return None if why is None else f"ngsolve/xfem are not importable ({why}); {INSTALL}"


def _peers(cut_records, memory_gib, down_to, progress) -> dict:
    """ngsxfem at the cut levels that ran (see the module docstring), with the ratio of totals."""
    missing = _peer_missing()
    if missing:
        progress(f"peers skipped: {missing}")
        print(f"note: ngsxfem comparison skipped: {missing}")
        return {"skipped": missing}
    rows = []
    for cf in cut_records:
        s = cf["level"]
        tets = structured_box(*BOX, spacing=s).n_tets
        avail = _available_gib()
        need = BYTES_PER_TET * tets / 2**30
        cap = memory_gib if avail is None else min(memory_gib, 0.9 * avail)
        row = {"level": s, "cutfem_total": cf["total"], "cutfem_solver": cf["solver"]}
        if s < down_to:
            row["skipped"] = f"finer than --peers-down-to {down_to:g} (the NGSolve mesh needs about {need:.1f} GiB)"
        elif need > cap:
            row["skipped"] = f"the NGSolve mesh of {tets} tets needs about {need:.1f} GiB > {cap:.1f} GiB"
        else:
            progress(f"ngsxfem, spacing {s}")
            try:
                ng = level_in_fresh_process("ngsxfem", s)
            except RuntimeError as exc:
                row["failed"] = str(exc)[-500:]
            else:
                row.update(ngsxfem=ng, ratio=ng["total"] / cf["total"],
                           same_problem=all(ng[k] == cf[k] for k in ("dofs", "active_tets", "interior_faces")))
                progress(f"  ngsxfem {ng['total']:.2f} s against cutfem {cf['total']:.2f} s: ratio {row['ratio']:.1f}")
        if "skipped" in row or "failed" in row:
            progress(f"  ngsxfem at {s}: {row.get('skipped') or row['failed'].splitlines()[-1]}")
        rows.append(row)
    return {"levels": rows, "note": "ngsxfem: NGSolve sparse Cholesky, one thread, one run a level; cutfem: its automatic "
                                   "solver, the fastest of its runs; ratio = ngsxfem / cutfem of the stage sums"}


# ---------------------------------------------------------------------------------------------
# the study
# ---------------------------------------------------------------------------------------------

def _best_of(kind: str, level, repeat: int, warm: bool = True) -> dict:
    """Run a level ``repeat`` times (fresh processes) and keep the fastest run; all the end-to-end
    times are kept in ``totals`` and their system CPU times in ``cpu_system_all``."""
    runs = [level_in_fresh_process(kind, level, warm) for _ in range(repeat)]
    best = min(runs, key=lambda r: r["total"])
    best["totals"] = [r["total"] for r in runs]
    best["cpu_system_all"] = [r["cpu_system"] for r in runs]
    return best


def _spread(r) -> str:
    t = r["totals"]
    return f"{r['total']:.2f} s" if len(t) == 1 else f"{r['total']:.2f} s (best of {len(t)}; {min(t):.2f}-{max(t):.2f})"


def _cut_runner(repeat, progress, warm: bool = True):
    def run_cut(s):
        progress(f"cut torus, spacing {s}" + (f" ({repeat} runs)" if repeat > 1 else ""))
        try:
            r = _best_of("cut", s, repeat, warm)
        except RuntimeError as exc:  # e.g. out of memory: recorded, not hidden
            progress(f"  failed: {str(exc).splitlines()[-1]}")
            return {"kind": "cut", "level": s, "failed": str(exc)[-500:]}
        progress(f"  {r['active_tets']} active tets, {r['dofs']} dofs: {_spread(r)}, {r['peak_memory_gib']:.2f} GiB, "
                 f"{r['solver']} ({r['iterations']} its), L2 error {r['l2_error']:.4e}")
        return r

    return run_cut


def run(out: Path, size: str = "quick", progress=None, peers: bool = False, limit: bool = False, bulk: bool = False,
        memory_gib: float = 20.0, peers_down_to: float = PEERS_DOWN_TO) -> dict:
    """The benchmark (see the module docstring).  Each level runs ``repeat`` times (1 for tiny and
    in ``limit`` mode, 3 otherwise) and the fastest run is kept: the spread on this kind of machine
    is the kernel's page-fault time, not the algorithm (the user CPU time varies far less), and the
    minimum is the least noisy estimate of the cost.  The exponents are fitted to the kept runs;
    every run's total is in the JSON (``totals``)."""
    progress = progress or Progress("performance")
    repeat = 1 if limit else pick(size, 1, 3, 3)
    compile_bytecode()
    progress("memory bandwidth")
    bw = bandwidth_in_fresh_process(pick(size, 32, 200, 200))
    progress(f"  {bw['bandwidth'] / 1e9:.2f} GB/s (copy {bw['copy'] / 1e9:.2f}, triad {bw['triad'] / 1e9:.2f})")
    run_cut = _cut_runner(repeat, progress, warm=not limit)  # --limit: no second run beside a level near the memory limit
    summary = {"repeat": repeat, "bandwidth": bw}
    if limit:
        summary["limit"] = lim = limit_search(run_cut, memory_gib, available_gib=_available_gib, progress=progress)
        records = list(lim["levels"])
        progress(f"limit: {lim['stopped']}")
    else:
        spacings = pick(size, [0.2, 0.1], [0.1, 0.05, 0.025, 0.0125], [0.1, 0.05, 0.025, 0.0125, 0.00625, 0.003125])
        records = [run_cut(s) for s in spacings]
        ns = pick(size, [32, 64], [64, 128, 256, 512, 768], [64, 128, 256, 512, 768])
        for family in ("flipped", "perturbed"):
            for n in ns:
                progress(f"meshed torus {family}, n = {n}")
                records.append(_best_of(f"meshed-{family}", n, repeat))
                r = records[-1]
                progress(f"  {r['dofs']} dofs: {_spread(r)}, {r['peak_memory_gib']:.2f} GiB, {r['solver']}")
    ok = [r for r in records if "failed" not in r]
    cut = [r for r in ok if r["kind"] == "cut"]
    for r in cut:
        r["bounds"] = stage_bounds(r, bw["bandwidth"])
    summary["levels"] = records
    summary["exponents"] = {"cut": scaling_exponents(cut, "active_tets", stages=CUT_STAGES[1:])}  # background: microseconds
    from_target = [r for r in cut if r["level"] <= EXPONENT_FROM]  # the issue's range: 0.025 down to the finest
    if len(from_target) > 3:
        summary["exponents"][f"cut from {EXPONENT_FROM:g}"] = scaling_exponents(from_target, "active_tets", finest=len(from_target))
    if not limit:
        spacing = pick(size, 0.1, 0.0125, 0.0125)
        progress(f"compiled references, cut torus at spacing {spacing}")
        summary["compiled_references"] = references_in_fresh_process(spacing)
        summary["stage_targets"] = stage_targets(cut, summary["compiled_references"])
        summary["commands"] = command_times(size, repeat, progress)
    if peers:
        summary["peers"] = _peers(cut, memory_gib, peers_down_to, progress)
    if bulk:
        rows = []
        for s in pick(size, [0.2], [0.1, 0.05, 0.025], BULK_FULL):
            progress(f"bulk poisson-cut on the solid torus, spacing {s}")
            try:
                rows.append(bulk_level(s))
            except RuntimeError as exc:
                progress(f"  failed: {str(exc).splitlines()[-1]}")
                rows.append({"kind": "bulk-poisson", "level": s, "failed": str(exc)[-500:]})
                continue
            progress(f"  {rows[-1]['dofs']} unknowns: {rows[-1]['wall']:.2f} s, {rows[-1]['peak_memory_gib']:.2f} GiB")
        summary["bulk"] = rows
        summary["exponents"]["bulk"] = scaling_exponents([r for r in rows if "failed" not in r], "dofs", time_key="wall")
    save_json(out, "performance", summary)
    _plot(out, ok, summary)
    _plot_bounds(out, cut, summary)
    _print_tables(ok, summary)
    return summary


def _fmt(v, spec):
    return "--" if v is None or not np.isfinite(v) else format(v, spec)


def _print_tables(records, summary):
    """The kept (fastest) run of each level with the slowest run's total beside it; the bounds and
    ratios per stage of the cut levels; the exponents; ngsxfem and the bulk levels when run."""
    print(f"{'kind':18s} {'level':>8s} {'dofs':>8s} {'tets':>8s} {'total s':>8s} {'slowest':>8s} {'user s':>7s} {'sys s':>6s} {'GiB':>6s}  stages")
    for r in records:
        stages = " ".join(f"{k}={v:.2f}" for k, v in r["time"].items())
        print(f"{r['kind']:18s} {r['level']:>8g} {r['dofs']:>8d} {r.get('active_tets', 0):>8d} {r['total']:>8.2f} "
              f"{max(r['totals']):>8.2f} {r['cpu_user']:>7.2f} {r['cpu_system']:>6.2f} {r['peak_memory_gib']:>6.2f}  {stages}")
    warm = [r for r in records if "warm" in r]
    if warm:
        print("\nthe same levels run again in their process: the stages' own times, and the start-up the first run "
              "paid inside them")
        print(f"{'kind':18s} {'level':>8s} {'warm s':>8s} {'start s':>8s} {'faults':>8s}  stages")
        for r in warm:
            stages = " ".join(f"{k}={v:.3f}" for k, v in r["warm"]["time"].items())
            print(f"{r['kind']:18s} {r['level']:>8g} {r['warm']['total']:>8.2f} {r['start_up']:>8.2f} "
                  f"{r['warm']['page_faults']:>8d}  {stages}")
    cut = [r for r in records if r["kind"] == "cut"]
    if cut:
        bw = summary["bandwidth"]["bandwidth"]
        both = all("warm" in r for r in cut)
        print(f"\nlower bounds from the memory traffic at {bw / 1e9:.2f} GB/s (estimates, see cutfem.studies.performance_bounds): "
              "bound [ms] and measured / bound per stage, " + ("the stage's own time (run again in its process) and "
                                                                "in parentheses a fresh process's" if both else "in a fresh process"))
        print(f"{'level':>8s} " + " ".join(f"{s:>21s}" for s in CUT_STAGES))
        for r in cut:
            b = r["bounds"]
            cells = (f"{b[s]['bound'] * 1e3:8.2f} " + ("    --" if b[s]["ratio"] is None else f"{b[s]['ratio']:5.0f}x" + (
                f" ({b[s]['ratio_fresh']:.0f}x)" if both else "")) for s in CUT_STAGES)
            print(f"{r['level']:>8g} " + " ".join(f"{c:>21s}" for c in cells))
    if cut and all("stage_cpu" in r for r in cut):
        print("\nsystem time and page faults per stage (the kernel's first touches of memory): system s / thousand faults")
        print(f"{'level':>8s} " + " ".join(f"{s:>15s}" for s in CUT_STAGES))
        for r in cut:
            cells = (f"{r['stage_cpu'][s]['system']:6.2f} / {r['stage_cpu'][s]['faults'] / 1e3:6.0f}" if s in r["stage_cpu"] else "--"
                     for s in CUT_STAGES)
            print(f"{r['level']:>8g} " + " ".join(f"{c:>15s}" for c in cells))
    for name, e in summary["exponents"].items():
        if e:
            stages = " ".join(f"{k}={v:.2f}" for k, v in e.get("stages", {}).items())
            print(f"\nexponents ({name}, against {e['x']}, levels {e['levels']}): time {_fmt(e.get('time'), '.2f')}, "
                  f"user time {_fmt(e.get('user_time'), '.2f')}, memory {_fmt(e.get('memory'), '.2f')}" + (f"; stages {stages}" if stages else ""))
        else:
            print(f"\nexponents ({name}): fewer than three levels ran")
    if summary.get("compiled_references"):
        refs = summary["compiled_references"]
        print(f"\ncompiled references: the same operation on the same data by a compiled library (cut torus at spacing "
              f"{refs[0]['spacing']:g}, {refs[0]['unknowns']} unknowns; medians of {refs[0]['repeat']}); per thread = "
              "reference / cutfem on one thread")
        width = max(len(r["operation"]) for r in refs)
        rwidth = max(len(r["reference"]) for r in refs)
        print(f"  {'operation':{width}s} {'cutfem ms':>10s} {'1 thread':>9s}  {'reference':{rwidth}s} {'ms':>8s} {'per thread':>10s} {'difference':>10s}")
        for r in refs:
            print(f"  {r['operation']:{width}s} {1e3 * r['cutfem']:10.2f} {1e3 * r['cutfem_one_thread']:9.2f}  {r['reference']:{rwidth}s} "
                  f"{1e3 * r['reference_time']:8.2f} {r['per_thread']:10.2f} {r['difference']:10.1e}")
    if summary.get("stage_targets"):
        targets = summary["stage_targets"]
        level = next(iter(targets.values()))["level"]
        print(f"\nevery stage within 2 times of its bound? own time / memory-traffic bound at spacing {level:g}; "
              "cutfem on one thread / the compiled reference (the largest over the stage's rows above; the solve by its kernels)")
        for stage, t in targets.items():
            compiled = "no reference" if t["compiled_ratio"] is None else f"{t['compiled_ratio']:.2f}"
            share = f" (the exact field's evaluation {100 * t['exact_share']:.0f} % of the stage)" if "exact_share" in t else ""
            print(f"  {stage:10s} traffic {_fmt(t['traffic_ratio'], '.0f'):>4s}x   compiled {compiled:>12s}   "
                  f"{'within 2x' if t['within_2x'] else 'not within 2x'}{share}")
    if summary.get("commands"):
        print("\nend to end through the command line (a fresh process a run, start-up included; median of the runs, range)")
        width = max(len(c["command"]) for c in summary["commands"])
        for c in summary["commands"]:
            verdict = "" if c["target"] is None else f"  target {c['target']:g} s: {'met' if c['met'] else 'not met'}"
            print(f"  {c['command']:{width}s} {c['median']:7.2f} s ({c['min']:.2f}-{c['max']:.2f}), {c['peak_memory_gib']:.2f} GiB{verdict}")
    peers = summary.get("peers")
    if peers is not None:
        print()
        if "skipped" in peers:
            print(f"ngsxfem: skipped ({peers['skipped']})")
        for p in peers.get("levels", []):
            if "ratio" in p:
                print(f"ngsxfem {p['level']:>8g}: {p['ngsxfem']['total']:.2f} s against cutfem {p['cutfem_total']:.2f} s, "
                      f"ratio {p['ratio']:.1f}, same problem {p['same_problem']}, peak {p['ngsxfem']['peak_memory_gib']:.2f} GiB")
            else:
                print(f"ngsxfem {p['level']:>8g}: {p.get('skipped') or p['failed'].splitlines()[-1]}")
    if summary.get("bulk"):
        print(f"\n{'bulk poisson':>12s} {'unknowns':>9s} {'wall s':>7s} {'GiB':>6s} {'s/M':>7s} {'GiB/M':>6s}  stages")
        for r in summary["bulk"]:
            if "failed" in r:
                print(f"{r['level']:>12g} failed")
                continue
            stages = " ".join(f"{k}={v:.2f}" for k, v in r["time"].items())
            print(f"{r['level']:>12g} {r['dofs']:>9d} {r['wall']:>7.2f} {r['peak_memory_gib']:>6.2f} {r['seconds_per_million']:>7.2f} "
                  f"{r['gib_per_million']:>6.2f}  {stages}")
    if "limit" in summary:
        lim = summary["limit"]
        big, nxt = lim["largest"], lim["next"]
        print(f"\nlimit {lim['memory_gib']:g} GiB: stopped: {lim['stopped']}")
        if big:
            print(f"  largest level run: spacing {big['level']:g}, {big['active_tets']} active tets, {big['peak_memory_gib']:.2f} GiB; "
                  f"next: spacing {nxt['spacing']:g}, predicted {nxt['active_tets']:.0f} tets, {nxt['peak_memory_gib']:.2f} GiB")


@figure_style
def _plot(out, records, summary):
    fig, axes = new_figure(PAGE_WIDTH, 3.2, nrows=1, ncols=2)
    ng = [p["ngsxfem"] for p in summary.get("peers", {}).get("levels", []) if "ngsxfem" in p]
    series = [(kind, [r for r in records if r["kind"] == kind]) for kind in ("cut", "meshed-flipped", "meshed-perturbed")]
    for (kind, rs), marker in zip(series + [("ngsxfem", ng)], ("o", "s", "^", "D")):
        if not rs:
            continue
        x = [r["dofs"] if kind.startswith("meshed") else r["active_tets"] for r in rs]
        label = {"cut": "cut torus", "ngsxfem": "ngsxfem, cut torus"}.get(kind, kind.replace("-", ", "))
        for ax, key in zip(axes, ("total", "peak_memory_gib")):
            y = [r[key] for r in rs]
            ax.loglog(x, y, marker=marker, label=f"{label}: {fitted_exponent(x[-3:], y[-3:]):.2f}" if len(x) >= 3 else label)
    for ax, title in zip(axes, ("time [s]", "peak memory [GiB]")):
        ax.set_xlabel("active tets (cut) / nodes (meshed)")
        ax.set_ylabel(title)
        ax.grid(True, which="both", alpha=0.3)
        # the curves rise from the lower left: this corner stays clear
        ax.legend(loc="upper left", title="exponent, 3 finest levels")
    axes[0].set_title("all stages, imports excluded")
    axes[1].set_title("peak resident memory of the process")
    save_figure(fig, out, "performance_scaling")


@figure_style
def _plot_bounds(out, cut, summary):
    """The stage's own time (run again in its process) / bound per stage of the cut levels; with
    the compiled references, the target per stage (:func:`stage_targets`: both ratios of each
    stage against the line at 2); with bulk levels, their time and memory per million unknowns."""
    bulk = [r for r in summary.get("bulk", []) if "failed" not in r]
    targets = summary.get("stage_targets") or {}
    panels = 1 + bool(targets) + bool(bulk)
    fig, axes = new_figure(PAGE_WIDTH, 3.2 if panels < 3 else 6.0, nrows=1 if panels < 3 else 2, ncols=min(panels, 2), squeeze=False)
    axes = list(axes.ravel())
    if panels == 3:
        axes[3].remove()
    ax = axes[0]
    x = [r["active_tets"] for r in cut]
    for stage in CUT_STAGES[1:]:
        ax.loglog(x, [r["bounds"][stage]["ratio"] for r in cut], marker="o", label=stage)
    ax.set_xlabel("active tets")
    ax.set_ylabel("stage time / memory-traffic bound")
    ax.set_title(f"cut torus, stages warm; {summary['bandwidth']['bandwidth'] / 1e9:.1f} GB/s")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(ncols=2)
    if targets:
        _plot_stage_targets(axes[1], targets)
    if bulk:
        ax = axes[1 + bool(targets)]
        n = [r["dofs"] for r in bulk]
        per_million = ([r["seconds_per_million"] for r in bulk], [r["gib_per_million"] for r in bulk])
        ax.semilogx(n, per_million[0], marker="o", label="wall time [s]")
        ax.semilogx(n, per_million[1], marker="s", label="peak memory [GiB]")
        ax.set_xlabel("unknowns")
        ax.set_ylabel("per million unknowns")
        ax.set_title("poisson-cut, solid torus")
        ax.set_ylim(0, 1.3 * max(max(v) for v in per_million))  # room for the legend above the first points
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper right")  # the values fall from the upper left
    save_figure(fig, out, "performance_bounds")


def _plot_stage_targets(ax, targets: dict) -> None:
    """Per stage, its own time over its memory-traffic bound and its time on one thread over the
    compiled reference's, as horizontal bars on a log axis, with the target 2 as a line."""
    stages = [s for s in CUT_STAGES if s in targets]  # the stages' order (a JSON file may have sorted them)
    y = np.arange(len(stages))
    for k, (key, label) in enumerate((("traffic_ratio", "own time / traffic bound"), ("compiled_ratio", "one thread / compiled reference"))):
        values = [targets[s][key] for s in stages]
        have = [i for i, v in enumerate(values) if v is not None]
        ax.barh(y[have] + (0.2 if k else -0.2), [values[i] for i in have], height=0.38, label=label)
    ax.axvline(2.0, color="k", linestyle="--", linewidth=1, label="target 2")
    ax.set_xscale("log")
    ax.set_yticks(y, [s + ("" if targets[s]["within_2x"] else " (not met)") for s in stages])
    ax.invert_yaxis()
    ax.set_xlabel(f"time ratio (spacing {targets[stages[0]]['level']:g})")
    ax.set_title("every stage within 2 times?")
    ax.grid(True, axis="x", which="both", alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), fontsize="small")


def _positive_gib(text: str) -> float:
    import argparse

    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number of GiB, got {text!r}")
    return value


def main(argv=None) -> int:
    """``python -m cutfem.studies.performance [--peers] [--limit] [--bulk] [--memory-gib G]
    [--peers-down-to S]`` plus the usual study options (``--out``, the size flags)."""
    import argparse

    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--peers", action="store_true", help="run ngsxfem on the same cut levels (needs ngsolve and xfem)")
    p.add_argument("--limit", action="store_true", help="halve the spacing until the next cut level is predicted not to fit in --memory-gib")
    p.add_argument("--bulk", action="store_true", help="also time poisson-cut on the solid torus")
    p.add_argument("--memory-gib", type=_positive_gib, default=20.0, help="memory limit of --limit and --peers in GiB (default 20)")
    p.add_argument("--peers-down-to", type=float, default=PEERS_DOWN_TO, help=f"finest spacing for ngsxfem (default {PEERS_DOWN_TO})")
    return study_main(run, "performance", p)(argv)


if __name__ == "__main__":
    sys.exit(main())
