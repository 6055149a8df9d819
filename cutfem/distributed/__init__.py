"""Distributed runs on MPI and PETSc (docs/math.md §19): a structured box in slabs of cell layers,
an unstructured mesh by recursive bisection of its cells (:mod:`~cutfem.distributed.partition`,
:mod:`~cutfem.distributed.unstructured`), the unknowns in the serial numbering owned by one rank each
and the system on PETSc (:mod:`~cutfem.distributed.system`), the problems that run on several
ranks (:data:`DISTRIBUTED_LEVELS`).  Importing it imports neither mpi4py nor petsc4py."""

from __future__ import annotations

import importlib

from ..runs.registry import get_problem
from .launch import launched, launched_rank, launched_size

__all__ = ["DISTRIBUTED_LEVELS", "DISTRIBUTED_ORDERS", "distributed_level", "distributed_orders", "distributed_params", "launched",
           "launched_rank", "launched_size"]

#: the problems that run on several ranks: name -> "module:function" of one distributed level,
#: called with the problem's parameters like its serial level
DISTRIBUTED_LEVELS = {
    "poisson-cut": "cutfem.distributed.poisson:poisson_cut_level",
    "laplace-beltrami-cut": "cutfem.distributed.laplace_beltrami:laplace_beltrami_cut_level",
    "mean-curvature-cut": "cutfem.distributed.mean_curvature:mean_curvature_cut_level",
    "interface-poisson-cut": "cutfem.distributed.interface_poisson:interface_poisson_cut_level",
    "stokes-cut": "cutfem.distributed.stokes:stokes_cut_level",
}

#: the problems whose distributed level also assembles P2 fields (on the structured box's slabs,
#: docs/math.md §19), and takes ``order``; the others are P1 on the planar cut
DISTRIBUTED_ORDERS = {"poisson-cut": (1, 2), "laplace-beltrami-cut": (1, 2)}


def distributed_orders(name: str) -> tuple:
    """The orders the distributed level of problem ``name`` runs at."""
    return DISTRIBUTED_ORDERS.get(name, (1,))


def distributed_level(name: str):
    """The function that solves one level of problem ``name`` on all ranks, or None when the
    problem is not distributed."""
    target = DISTRIBUTED_LEVELS.get(name)
    if target is None:
        return None
    module, function = target.split(":")
    return getattr(importlib.import_module(module), function)


def distributed_params(name: str, given: dict) -> dict:
    """The resolved parameters of problem ``name`` (its defaults with ``given``) for its distributed
    level: with ``order`` for a level of several orders (:data:`DISTRIBUTED_ORDERS`), without it
    for a P1 level, where it must be 1 (the runner refuses --order 2 on several ranks)."""
    params = get_problem(name).resolve(given)
    order = params.pop("order", 1)
    orders = distributed_orders(name)
    if order not in orders:
        raise ValueError(f"{name}: the distributed level is P1 (order 1), got order={order}; the problems distributed at "
                         f"order 2: {', '.join(n for n, o in DISTRIBUTED_ORDERS.items() if 2 in o)}")
    return params | ({"order": order} if len(orders) > 1 else {})
