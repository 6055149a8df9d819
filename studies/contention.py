"""Speed on a shared machine: cutfem's default threads against one thread, and a Python script
against the command line, each beside a busy process; and default threads against one thread on
an idle machine where the work is large.

    python -m cutfem.studies.contention [--out DIR] [--repeats N] [--quick]

Every case is a pair of commands run as fresh processes, in turn (A B, then B A, ...), and the
ratio is the median of the pairs' ratios of wall times, so a drift of the machine's speed cancels.
"Busy" starts one process that spins on a core (a Python loop, like ``yes > /dev/null``) before the
pair and stops it after.  One thread is ``NUMBA_NUM_THREADS=1``.  The cases:

* every registered problem at a mid level through ``cutfem run`` (busy): default / one thread;
* a preconditioned block solve from Python (busy): MINRES (scipy) on a stabilized P1-P1 Stokes-type
  saddle system in a cut ball, the velocity block preconditioned by :class:`GeometricMultigrid`
  and the pressure by its lumped mass, about 12.6 thousand unknowns (:func:`block_solve`; the
  ratio of its solve stage, timed inside the process, is reported beside the wall times);
* 200 small cuts in a loop from Python (busy): spheres of random centres in a box at spacing 0.2,
  each cut with its area (:func:`small_cuts`);
* ``cutfem.run("poisson-cut", levels=[0.05, 0.025])`` from a script against
  ``cutfem run poisson-cut --levels 0.05 0.025`` (busy);
* the cut torus at spacing 0.0125 and fictitious-domain Poisson at 0.025 (idle): default / one
  thread, which should stay below 1.

The targets (issue 45): busy, default / one thread <= 1.15 and script / command line <= 1.15; idle,
default / one thread < 1 where the work is large.  The table is printed and saved as
``contention.json`` and ``contention.md`` in the output folder.  This is a benchmark, never a test:
its figures depend on the machine and its hour.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

TARGET = 1.15

#: the mid level of each registered problem (its default levels' second finest or so)
MID_LEVELS = {
    "bulk-surface-cut": "0.05",
    "heat-surface-cut": "0.1",
    "interface-poisson-cut": "0.05",
    "laplace-beltrami-cut": "0.05",
    "laplace-beltrami-meshed": "64",
    "mean-curvature-cut": "0.025",
    "mean-curvature-meshed": "128",
    "poisson-cut": "0.05",
}

_SPIN = "while True:\n    pass\n"


def block_solve(spacing: float = 0.125) -> dict:
    """A stabilized equal-order Stokes-type system in the unit ball cut from a structured box,
    solved by MINRES with a block-diagonal preconditioner; returns the sizes, iterations and the
    solve stage's seconds.

    The system is [[A, B^T], [B, -C]] with A = diag(K, K, K), K the Nitsche-ghost-penalty Laplacian of
    a CutSpace on the ball (:func:`cutfem.fem.terms.stiffness`, :func:`~cutfem.fem.terms.nitsche`,
    :func:`~cutfem.fem.terms.face_jump_penalty`), B_i = -(d_i u, q) and C = h^2 (grad p, grad q)
    (Brezzi-Pitkaeranta); the preconditioner applies one cycle of :class:`GeometricMultigrid` on K to
    the three velocity components at once and the inverse lumped pressure mass."""
    import numpy as np
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    from cutfem.geometry.cut import NEG, cut_mesh
    from cutfem.fem.forms import assemble, bilinear_form
    from cutfem.fem.terms import face_jump_penalty, mass, nitsche, stiffness
    from cutfem.geometry.shapes import Sphere
    from cutfem.geometry.box import structured_box
    from cutfem.solvers.multigrid import GeometricMultigrid, lattice_indices
    from cutfem.fem.spaces import CutSpace

    cut = cut_mesh(structured_box([-1.2] * 3, [1.2] * 3, spacing=spacing), Sphere(1.0))
    V = CutSpace(cut, NEG)
    dx, ds, dg = cut.dx(NEG), cut.ds(), cut.dF(cut.ghost_facets(NEG))
    K = assemble(stiffness(dx) + nitsche(ds) + 0.1 * face_jump_penalty(dg, h_power=1), V).tocsr()
    G = [assemble(bilinear_form(lambda u, v, w, i=i: -u.grad[..., i] * v) * dx, V).tocsr() for i in range(3)]
    h = V.h
    C = (h * h) * assemble(stiffness(dx) + 0.1 * face_jump_penalty(dg, h_power=1), V).tocsr()
    Mp = np.asarray(assemble(mass(dx), V).sum(axis=1)).ravel()
    n = K.shape[0]
    S = sp.bmat([[K, None, None, G[0].T], [None, K, None, G[1].T], [None, None, K, G[2].T], [G[0], G[1], G[2], -C]], format="csr")
    rng = np.random.default_rng(0)
    b = S @ rng.standard_normal(S.shape[0])
    mg = GeometricMultigrid(K, lattice=lattice_indices(V), visits=(1,))  # a V-cycle: a fixed symmetric operator, as MINRES needs

    def precondition(r):
        z = np.empty_like(r)
        z[:3 * n] = mg.apply(np.ascontiguousarray(r[:3 * n].reshape(3, n).T)).T.ravel()
        z[3 * n:] = r[3 * n:] / Mp
        return z

    M = spla.LinearOperator(S.shape, matvec=precondition, dtype=float)
    iterations = [0]
    t0 = time.perf_counter()
    x, flag = spla.minres(S, b, M=M, rtol=1e-8, maxiter=2000, callback=lambda _: iterations.__setitem__(0, iterations[0] + 1))
    seconds = time.perf_counter() - t0
    return {"unknowns": int(S.shape[0]), "iterations": iterations[0], "flag": int(flag), "solve_seconds": seconds}


def small_cuts(count: int = 200, spacing: float = 0.2, seed: int = 0) -> float:
    """The summed area of ``count`` cuts of unit spheres with random centres (a user's loop of
    small cuts, each a few thousand tets)."""
    import numpy as np

    from cutfem.geometry.cut import cut_mesh
    from cutfem.geometry.shapes import Sphere
    from cutfem.geometry.box import structured_box

    box = structured_box([-1.6] * 3, [1.6] * 3, spacing=spacing)
    centres = np.random.default_rng(seed).uniform(-0.3, 0.3, (count, 3))
    return float(sum(cut_mesh(box, Sphere(1.0, center=c)).area for c in centres))


#: the interpreter the cases run with (``--python``: another checkout's environment, for a before/after)
PYTHON = [sys.executable]


def _python(code: str) -> list[str]:
    return [*PYTHON, "-c", code]


def _cli(*args: str) -> list[str]:
    return _python("import sys; from cutfem.runs.cli import entry; sys.argv = ['cutfem', *sys.argv[1:]]; entry()") + list(args)


def _environment(one_thread: bool) -> dict:
    """The caller's environment without cutfem's own settings, and NUMBA_NUM_THREADS=1 for one thread."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
    if one_thread:
        env["NUMBA_NUM_THREADS"] = "1"
    return env


def _run(command: list[str], env: dict) -> tuple[float, str]:
    t0 = time.perf_counter()
    done = subprocess.run(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed ({done.returncode}): {done.stderr.strip()[-800:]}")
    return seconds, done.stdout


class _Busy:
    """One process spinning on a core while the block runs."""

    def __init__(self, on: bool):
        self.on, self.process = on, None

    def __enter__(self):
        if self.on:
            self.process = subprocess.Popen(_python(_SPIN))
            time.sleep(0.3)  # let it take its core and show in the load
        return self

    def __exit__(self, *exc):
        if self.process is not None:
            self.process.kill()
            self.process.wait()


def pair(name: str, a: tuple, b: tuple, repeats: int, busy: bool, progress=print, stage=None) -> dict:
    """Median ratio A/B of interleaved runs of two (command, env) pairs; ``stage`` reads a time
    printed by the command (the last line of its standard output, JSON) to add the stage's ratio."""
    wall = {"a": [], "b": [], "ratio": []}
    stages = {"a": [], "b": [], "ratio": []}
    with _Busy(busy):
        _run(*a), _run(*b)  # warm-up: the kernels' cache, the page cache
        for r in range(repeats):
            order = (("a", a), ("b", b)) if r % 2 == 0 else (("b", b), ("a", a))
            got = {}
            for key, (command, env) in order:
                got[key] = _run(command, env)
            for key in ("a", "b"):
                wall[key].append(got[key][0])
                if stage:
                    stages[key].append(stage(got[key][1]))
            wall["ratio"].append(wall["a"][-1] / wall["b"][-1])
            if stage:
                stages["ratio"].append(stages["a"][-1] / stages["b"][-1])
    row = {"case": name, "busy": busy, "a": statistics.median(wall["a"]), "b": statistics.median(wall["b"]),
           "ratio": statistics.median(wall["ratio"]), "ratio_min": min(wall["ratio"]), "ratio_max": max(wall["ratio"]), "runs": repeats}
    if stage:
        row.update(stage_a=statistics.median(stages["a"]), stage_b=statistics.median(stages["b"]), stage_ratio=statistics.median(stages["ratio"]))
    progress(f"{name}: {row['a']:.2f} s / {row['b']:.2f} s = {row['ratio']:.2f} ({row['ratio_min']:.2f}-{row['ratio_max']:.2f})"
             + (f"; stage {row['stage_a']:.2f} / {row['stage_b']:.2f} s = {row['stage_ratio']:.2f}" if stage else ""))
    return row


def cases(quick: bool) -> list[dict]:
    """The cases: name, the two commands (default first), whether busy, the target and its sense."""
    out = []
    for problem, level in sorted(MID_LEVELS.items()):
        flag = "--levels"
        command = _cli("run", problem, flag, level)
        out.append(dict(name=f"{problem} {level}, default / one thread", a=command, b=command, one_thread_b=True, busy=True, target="<= 1.15"))
    block = [*PYTHON, __file__, "--case", "block"]
    out.append(dict(name="block solve from Python (MINRES + multigrid), default / one thread", a=block, b=block, one_thread_b=True, busy=True,
                    target="<= 1.15", stage=True))
    loop = [*PYTHON, __file__, "--case", "cuts"]
    out.append(dict(name="200 small cuts in a loop from Python, default / one thread", a=loop, b=loop, one_thread_b=True, busy=True, target="<= 1.15"))
    out.append(dict(name="poisson-cut 0.05 0.025, script / command line",
                    a=_python("import cutfem; cutfem.run('poisson-cut', levels=[0.05, 0.025])"),
                    b=_cli("run", "poisson-cut", "--levels", "0.05", "0.025"), one_thread_b=False, busy=True, target="<= 1.15"))
    if not quick:
        for problem, level in (("mean-curvature-cut", "0.0125"), ("poisson-cut", "0.025")):
            command = _cli("run", problem, "--levels", level)
            out.append(dict(name=f"{problem} {level} idle, default / one thread", a=command, b=command, one_thread_b=True, busy=False, target="< 1"))
    return out


def _stage(stdout: str) -> float:
    return float(json.loads(stdout.strip().splitlines()[-1])["solve_seconds"])


def _met(row) -> bool:
    value = row.get("stage_ratio", row["ratio"]) if row["busy"] else row["ratio"]
    return value <= TARGET if row["target"].startswith("<=") else value < 1.0


def markdown(rows: list[dict], when: str) -> str:
    lines = [f"Measured {when} (medians of interleaved fresh processes; A / B).", "",
             "| case | busy | A [s] | B [s] | A / B | range | target | met |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ratio = f"{r['ratio']:.2f}" + (f" (solve stage {r['stage_ratio']:.2f})" if "stage_ratio" in r else "")
        lines.append(f"| {r['case']} | {'yes' if r['busy'] else 'no'} | {r['a']:.2f} | {r['b']:.2f} | {ratio} | "
                     f"{r['ratio_min']:.2f}-{r['ratio_max']:.2f} | {r['target']} | {'yes' if r['met'] else 'no'} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m cutfem.studies.contention", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/contention"), help="output folder (default out/contention)")
    parser.add_argument("--repeats", type=int, default=5, help="interleaved pairs per case (default 5)")
    parser.add_argument("--quick", action="store_true", help="the busy cases only")
    parser.add_argument("--only", default=None, help="run only the cases whose name contains this text")
    parser.add_argument("--python", default=sys.executable,
                        help="the Python interpreter the cases run with (another checkout's environment, to measure before and after)")
    parser.add_argument("--case", choices=["block", "cuts"], help=argparse.SUPPRESS)  # one case's work, in its own process
    args = parser.parse_args(argv)
    if args.case:
        print(json.dumps(block_solve() if args.case == "block" else {"area": small_cuts()}))
        return 0
    PYTHON[0] = args.python
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    rows = []
    progress = lambda m: print(f"[contention] {m}", file=sys.stderr, flush=True)
    when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    for case in cases(args.quick):
        if args.only and args.only not in case["name"]:
            continue
        a = (case["a"], _environment(False))
        b = (case["b"], _environment(case["one_thread_b"]))
        row = pair(case["name"], a, b, args.repeats, case["busy"], progress, _stage if case.get("stage") else None)
        row["target"] = case["target"]
        row["met"] = _met(row)
        rows.append(row)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "contention.json").write_text(json.dumps({"measured": when, "cpus": len(os.sched_getaffinity(0)), "python": args.python, "rows": rows}, indent=2) + "\n")
    text = markdown(rows, when)
    (args.out / "contention.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
