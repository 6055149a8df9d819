"""Under an MPI launcher a problem that is not distributed (or not at the order asked) is refused on
several ranks (never run N times over), and the launcher's variables are read without importing
mpi4py."""

import pytest

import cutfem as cf
from cutfem.distributed import DISTRIBUTED_LEVELS, DISTRIBUTED_ORDERS, distributed_params, launched, launched_rank, launched_size
from cutfem.runs.registry import ProblemError, available_problems


def test_launcher_variables(monkeypatch):
    for v in ("OMPI_COMM_WORLD_SIZE", "OMPI_COMM_WORLD_RANK", "PMI_SIZE", "PMI_RANK", "PMIX_SIZE", "PMIX_RANK", "MPI_LOCALNRANKS"):
        monkeypatch.delenv(v, raising=False)
    assert not launched() and launched_size() == 1 and launched_rank() == 0
    monkeypatch.setenv("PMI_SIZE", "3")
    monkeypatch.setenv("PMI_RANK", "2")
    assert launched() and launched_size() == 3 and launched_rank() == 2


def test_problems_not_distributed_are_refused_on_several_ranks(monkeypatch):
    monkeypatch.setenv("OMPI_COMM_WORLD_SIZE", "2")
    monkeypatch.setenv("OMPI_COMM_WORLD_RANK", "0")
    with pytest.raises(ProblemError, match=r"bulk-surface-cut is not distributed: run it on one rank.*poisson-cut"):
        cf.run("bulk-surface-cut", levels=[0.2])


def test_distributed_problems_are_registered():
    assert set(DISTRIBUTED_LEVELS) <= set(available_problems())


@pytest.mark.parametrize("name", ["mean-curvature-cut", "interface-poisson-cut"])  # stokes-cut is P1 only
def test_order_two_is_refused_on_several_ranks(monkeypatch, name):
    """The distributed levels but poisson-cut's and laplace-beltrami-cut's are P1 on the planar cut:
    --order 2 on several ranks names the fix and the problems that are distributed at order 2."""
    assert DISTRIBUTED_ORDERS == {"poisson-cut": (1, 2), "laplace-beltrami-cut": (1, 2)}
    monkeypatch.setenv("OMPI_COMM_WORLD_SIZE", "2")
    monkeypatch.setenv("OMPI_COMM_WORLD_RANK", "0")
    with pytest.raises(ProblemError, match=rf"{name} --order 2 is not distributed.*run it on one rank.*at order 2: poisson-cut, laplace-beltrami-cut"):
        cf.run(name, levels=[0.2], order=2)
    with pytest.raises(ValueError, match=rf"{name}: the distributed level is P1.*at order 2: poisson-cut, laplace-beltrami-cut"):
        distributed_params(name, {"order": 2})
