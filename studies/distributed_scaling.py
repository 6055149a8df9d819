"""Scaling of the distributed fictitious-domain Poisson problem: the same level on 1 and 2 ranks.

    python -m cutfem.studies.distributed_scaling [--ranks 1 2] [--spacing 0.0125] [--out DIR] [--tiny]

For each rank count a fresh ``mpiexec -n N python -m cutfem.studies.distributed_scaling --worker``
solves ``poisson-cut`` on the solid torus (:func:`cutfem.distributed.poisson.poisson_cut_level`,
CG + GAMG), after a warm-up level at spacing 0.2 that compiles the kernels.  Spacing 0.0125 gives
about 3 million unknowns.  Per rank count it records the unknowns, the stage times (the slowest
rank's: geometry = partition and cuts, assembly = local assembly, exchange and PETSc matrix, solve,
errors), the GAMG iterations and each rank's peak resident memory, and writes
``scaling_N.json``; the driver adds ``distributed_scaling.md``, a table with the speed-up of
assembly + solve over one rank.  The goals (issue 50): at least 1.6 times faster on 2 ranks than on
1 at >= 1M unknowns, iterations flat under refinement, a rank's memory at most 1.3 / N of the
serial one plus its ghost layer.  This is a benchmark, never a test: its figures depend on the
machine and on what else runs on it; run it on an idle machine.  Under mpiexec as root, set
``OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1``.
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
from cutfem.distributed.poisson import poisson_cut_level


def scaling_record(comm, spacing: float) -> dict:
    """One timed level of poisson-cut on the torus on the ranks of ``comm`` (a warm-up level at
    0.2 first), with each rank's peak resident memory in MiB (``memory_mib``, rank order)."""
    p = distributed_params("poisson-cut", {"surface": "torus", "solver": "cg-amg"})
    poisson_cut_level(0.2, **p, comm=comm)  # compiles the kernels; not recorded
    rec = poisson_cut_level(spacing, **p, comm=comm)
    rec["spacing"] = spacing
    rec["memory_mib"] = comm.allgather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
    return rec


def _worker(spacing: float, out: Path) -> None:
    MPI, _ = engine()
    comm = MPI.COMM_WORLD
    rec = scaling_record(comm, spacing)
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        (out / f"scaling_{comm.size}.json").write_text(json.dumps(rec, indent=2))


def table(records) -> str:
    """The markdown table of the records (one per rank count), speed-ups against the first."""
    head = "| ranks | unknowns | geometry s | assembly s | solve s | errors s | iterations | speed-up (assembly + solve) | peak memory per rank MiB |"
    lines = [head, "|" + "---|" * 9]
    base = None
    for r in records:
        t = r["time"]
        work = t["assembly"] + t["solve"]
        base = work if base is None else base
        lines.append(f"| {r['ranks']} | {r['dofs']:,} | {t['geometry']:.2f} | {t['assembly']:.2f} | {t['solve']:.2f} | "
                     f"{t['errors']:.2f} | {r['solver_iterations']} | {base / work:.2f} | "
                     f"{', '.join(f'{m:.0f}' for m in r['memory_mib'])} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m cutfem.studies.distributed_scaling", description=__doc__.split("\n\n")[0])
    parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2], help="rank counts (default 1 2)")
    parser.add_argument("--spacing", type=float, default=0.0125, help="background spacing (default 0.0125: about 3M unknowns)")
    parser.add_argument("--tiny", action="store_true", help="spacing 0.1, a check that the study runs")
    parser.add_argument("--out", type=Path, default=Path("out/distributed_scaling"), help="output folder")
    parser.add_argument("--mpiexec", default="mpiexec", help="the MPI launcher (default mpiexec)")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)  # one rank count, under mpiexec
    args = parser.parse_args(argv)
    spacing = 0.1 if args.tiny else args.spacing
    if args.worker:
        _worker(spacing, args.out)
        return 0
    records = []
    for n in args.ranks:
        command = [args.mpiexec, "-n", str(n), *(["--oversubscribe"] if n > (os.cpu_count() or 1) else []), sys.executable,
                   "-m", "cutfem.studies.distributed_scaling", "--worker", "--spacing", str(spacing), "--out", str(args.out)]
        print(" ".join(command), file=sys.stderr, flush=True)
        subprocess.run(command, check=True)
        records.append(json.loads((args.out / f"scaling_{n}.json").read_text()))
    text = table(records)
    (args.out / "distributed_scaling.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
