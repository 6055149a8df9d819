"""One script on one process or on N ranks: fictitious-domain Poisson in a solid torus.

    python docs/examples/distributed_poisson.py                   one process, cutfem's solvers
    mpiexec -n 2 python docs/examples/distributed_poisson.py      2 ranks, PETSc (CG + GAMG, or LU)

``cf.run`` solves a registered problem at each level.  Started by an MPI launcher it runs the
problem's distributed levels: the box is split in slabs of cell layers, each rank cuts its slab
and the one layer of cells below it, assembles the cell terms of its own cells and each ghost-penalty
face once, and PETSc solves (docs/math.md §19).  The unknowns are numbered as in the serial run,
so the errors agree with it to about 1e-10 on any number of ranks.  Every rank returns the same
record; rank 0 prints.  Distributed runs need mpi4py and petsc4py (README, "Distributed runs").
"""

import cutfem as cf


def main(spacing=0.2):
    """The errors, unknowns and ranks of poisson-cut on the solid torus at one spacing."""
    rec = cf.run("poisson-cut", levels=[spacing], surface="torus").records[0]
    return {"h": rec["h"], "l2": rec["l2_error"], "h1": rec["h1_error"], "dofs": rec["dofs"], "ranks": rec.get("ranks", 1),
            "engine": rec.get("engine", "cutfem")}


if __name__ == "__main__":
    result = cf.run("poisson-cut", levels=[0.2, 0.1, 0.05], surface="torus")
    if cf.launched_rank() == 0:
        print(result.table())
        rec = result.records[-1]
        print(f"solved by {rec.get('engine', 'cutfem')} ({rec['solver']}) on {rec.get('ranks', 1)} rank(s)")
