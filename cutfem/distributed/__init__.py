"""Distributed runs on MPI and PETSc (docs/math.md §19): a structured box in slabs of cell layers
(:mod:`~cutfem.distributed.partition`), the unknowns in the serial numbering owned by one rank each
and the system on PETSc (:mod:`~cutfem.distributed.system`), the problems that run on several
ranks (:data:`DISTRIBUTED_LEVELS`).  Importing it imports neither mpi4py nor petsc4py."""

from __future__ import annotations

import importlib

from .launch import launched, launched_rank, launched_size

__all__ = ["DISTRIBUTED_LEVELS", "distributed_level", "launched", "launched_rank", "launched_size"]

#: the problems that run on several ranks: name -> "module:function" of one distributed level,
#: called with the problem's parameters like its serial level
DISTRIBUTED_LEVELS = {
    "poisson-cut": "cutfem.distributed.poisson:poisson_cut_level",
    "laplace-beltrami-cut": "cutfem.distributed.laplace_beltrami:laplace_beltrami_cut_level",
    "mean-curvature-cut": "cutfem.distributed.mean_curvature:mean_curvature_cut_level",
    "interface-poisson-cut": "cutfem.distributed.interface_poisson:interface_poisson_cut_level",
}


def distributed_level(name: str):
    """The function that solves one level of problem ``name`` on all ranks, or None when the
    problem is not distributed."""
    target = DISTRIBUTED_LEVELS.get(name)
    if target is None:
        return None
    module, function = target.split(":")
    return getattr(importlib.import_module(module), function)
