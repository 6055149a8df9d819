"""Under mpiexec or not: the launcher's environment, and the imports of mpi4py and petsc4py.

Whether a process was started by an MPI launcher is read from the variables every launcher sets
(Open MPI's ``OMPI_COMM_WORLD_SIZE``, the PMI ``PMI_SIZE`` of MPICH and Intel MPI, Slurm's
``PMIX_SIZE`` ...), without importing mpi4py: a serial run never initializes MPI.  mpi4py and
petsc4py are imported on first use, with a message that says how to install them.
"""

from __future__ import annotations

import os
import sys

__all__ = ["launched", "launched_rank", "launched_size", "engine", "MPI_INSTALL"]

_SIZE_VARIABLES = ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_SIZE", "MPI_LOCALNRANKS")
_RANK_VARIABLES = ("OMPI_COMM_WORLD_RANK", "PMI_RANK", "PMIX_RANK")

#: how to get mpi4py and petsc4py, for the messages (README, "Distributed runs")
MPI_INSTALL = ("apt-get install -y --no-install-recommends petsc-dev, then in the virtual environment "
               "PETSC_DIR=/usr/lib/petscdir/petsc-real NUMPY_INCLUDE=$(python -c 'import numpy; print(numpy.get_include())') "
               "pip install -e \".[mpi]\" (README, 'Distributed runs')")


def launched() -> bool:
    """Whether this process was started by an MPI launcher (mpiexec, mpirun, srun)."""
    return any(v in os.environ for v in _SIZE_VARIABLES)


def launched_size() -> int:
    """The number of ranks the launcher started (1 when not launched)."""
    for v in _SIZE_VARIABLES:
        if v in os.environ:
            return int(os.environ[v])
    return 1


def launched_rank() -> int:
    """This process's rank as the launcher numbers it (0 when not launched)."""
    for v in _RANK_VARIABLES:
        if v in os.environ:
            return int(os.environ[v])
    return 0


def engine():
    """``(MPI, PETSc)``: the modules of mpi4py and petsc4py, PETSc initialized without the
    program's arguments (PETSc options come from the ``PETSC_OPTIONS`` variable).  An ImportError
    that says how to install them when they are missing."""
    try:
        from mpi4py import MPI
        import petsc4py
    except ImportError as exc:
        raise ImportError(f"distributed runs need mpi4py and petsc4py ({exc}); install them: {MPI_INSTALL}") from None
    if "petsc4py.PETSc" not in sys.modules:  # PETSc reads no options from the command line of cutfem
        petsc4py.init([sys.argv[0]] if sys.argv and sys.argv[0] else ["cutfem"])
    from petsc4py import PETSc

    return MPI, PETSc
