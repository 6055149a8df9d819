"""Scaling of the distributed levels: poisson-cut and mean-curvature-cut on 1 and 2 ranks.

    python -m cutfem.studies.distributed_scaling [--problem poisson-cut|mean-curvature-cut|all]
        [--ranks 1 2] [--spacing H] [--out DIR] [--tiny]

For each problem and rank count a fresh ``mpiexec -n N python -m cutfem.studies.distributed_scaling
--worker`` solves one level on the torus after a warm-up level at spacing 0.2 that compiles the
kernels: ``poisson-cut`` (:func:`cutfem.distributed.poisson.poisson_cut_level`) by CG + GAMG at
spacing 0.0125, about 2.7 million unknowns, and ``mean-curvature-cut``
(:func:`cutfem.distributed.mean_curvature.mean_curvature_cut_level`) by CG + PCMG on the lattice
hierarchy, its distributed default, at spacing 0.01, about 0.46 million unknowns a component and
1.4 million for the three.  Per problem and rank count it records the unknowns, the stage times
(the slowest rank's: geometry = partition and cuts, assembly = local assembly, exchange and PETSc
matrix, solve, errors), the iterations and each rank's peak resident memory, and writes
``scaling_PROBLEM_N.json``; the driver adds ``distributed_scaling.md``, a table with the speed-up
of assembly + solve over the first rank count of each problem.  The goals (issue 50): at least 1.6
times faster on 2 ranks than on 1 at >= 1M unknowns, iterations flat under refinement, a rank's
memory at most 1.3 / N of the serial one plus its ghost layer.  This is a benchmark, never a test:
its figures depend on the machine and on what else runs on it; run it on an idle machine.  Under
mpiexec as root, set ``OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
from pathlib import Path

from cutfem.distributed import distributed_params
from cutfem.distributed.launch import engine
from cutfem.distributed.mean_curvature import mean_curvature_cut_level
from cutfem.distributed.poisson import poisson_cut_level
from cutfem.memory import configure

#: problem -> (its distributed level, its parameters, the study's spacing, the fields of its unknowns)
PROBLEMS = {
    "poisson-cut": (poisson_cut_level, {"surface": "torus", "solver": "cg-amg"}, 0.0125, 1),
    "mean-curvature-cut": (mean_curvature_cut_level, {"surface": "torus", "solver": "cg-mg"}, 0.01, 3),
}

#: the warm-up level's spacing (compiles the kernels; not recorded) and the spacing of ``--tiny``
WARM_UP, TINY = 0.2, 0.1


def scaling_record(comm, spacing: float, problem: str = "poisson-cut") -> dict:
    """One timed level of ``problem`` on the torus on the ranks of ``comm`` (a warm-up level at
    :data:`WARM_UP` first), with each rank's peak resident memory in MiB (``memory_mib``, rank
    order) and the unknowns counting every component (``unknowns``: a vector field's three)."""
    level, given, _, components = PROBLEMS[problem]
    p = distributed_params(problem, given)
    level(WARM_UP, **p, comm=comm)
    rec = level(spacing, **p, comm=comm)
    rec["problem"], rec["spacing"], rec["unknowns"] = problem, spacing, rec["dofs"] * components
    rec["memory_mib"] = comm.allgather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
    return rec


def _worker(problem: str, spacing: float, out: Path) -> None:
    configure()  # a large run: the allocation settings of the serial studies (cutfem.memory)
    MPI, _ = engine()
    comm = MPI.COMM_WORLD
    rec = scaling_record(comm, spacing, problem)
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        (out / f"scaling_{problem}_{comm.size}.json").write_text(json.dumps(rec, indent=2))


def table(records) -> str:
    """The markdown table of the records (one per problem and rank count), speed-ups against the
    first record of the same problem."""
    head = ("| problem | ranks | unknowns | geometry s | assembly s | solve s | errors s | iterations | "
            "speed-up (assembly + solve) | peak memory per rank MiB |")
    lines = [head, "|" + "---|" * 10]
    base = {}
    for r in records:
        t = r["time"]
        work = t["assembly"] + t["solve"]
        first = base.setdefault(r["problem"], work)
        lines.append(f"| {r['problem']} | {r['ranks']} | {r['unknowns']:,} | {t['geometry']:.2f} | {t['assembly']:.2f} | "
                     f"{t['solve']:.2f} | {t['errors']:.2f} | {r['solver_iterations']} | {first / work:.2f} | "
                     f"{', '.join(f'{m:.0f}' for m in r['memory_mib'])} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m cutfem.studies.distributed_scaling", description=__doc__.split("\n\n")[0])
    parser.add_argument("--problem", choices=[*PROBLEMS, "all"], default="poisson-cut",
                        help="the problem, or all of them (default poisson-cut)")
    parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2], help="rank counts (default 1 2)")
    parser.add_argument("--spacing", type=float, default=None,
                        help="background spacing (default the problem's: 0.0125 for poisson-cut, 0.01 for mean-curvature-cut)")
    parser.add_argument("--tiny", action="store_true", help=f"spacing {TINY}, a check that the study runs")
    parser.add_argument("--out", type=Path, default=Path("out/distributed_scaling"), help="output folder")
    parser.add_argument("--mpiexec", default="mpiexec", help="the MPI launcher (default mpiexec)")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)  # one problem and rank count, under mpiexec
    args = parser.parse_args(argv)
    problems = list(PROBLEMS) if args.problem == "all" else [args.problem]
    if args.worker:
        _worker(problems[0], args.spacing, args.out)
        return 0
    records = []
    for problem in problems:
        spacing = TINY if args.tiny else args.spacing if args.spacing is not None else PROBLEMS[problem][2]
        for n in args.ranks:
            command = [args.mpiexec, "-n", str(n), *(["--oversubscribe"] if n > (os.cpu_count() or 1) else []), sys.executable,
                       "-m", "cutfem.studies.distributed_scaling", "--worker", "--problem", problem, "--spacing", str(spacing),
                       "--out", str(args.out)]
            print(" ".join(command), file=sys.stderr, flush=True)
            subprocess.run(command, check=True)
            records.append(json.loads((args.out / f"scaling_{problem}_{n}.json").read_text()))
    text = table(records)
    (args.out / "distributed_scaling.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
