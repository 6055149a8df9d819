"""poisson-cut and laplace-beltrami-cut at order 2 on MPI and PETSc (docs/math.md §19), run under
mpiexec at 1, 2 and 4 ranks and at 1 rank by a plain pytest (skipped without mpi4py and petsc4py):
the unknowns, the cut's sizes and the errors of the serial order-2 run, with ranks that own no layer
or no active cell, and the iterations of CG with the lattice multigrid.

Every rank runs every test in the same order (the tests are collective); sizes below the number of
ranks run on the first ranks (a split communicator)."""

import json

import pytest

pytest.importorskip("mpi4py")
pytest.importorskip("petsc4py")

from cutfem.distributed import distributed_params  # noqa: E402
from cutfem.distributed.launch import engine, launched  # noqa: E402
from cutfem.distributed.laplace_beltrami import laplace_beltrami_cut_level  # noqa: E402
from cutfem.distributed.poisson import poisson_cut_level  # noqa: E402
from cutfem.runs.cli import main  # noqa: E402
from cutfem.runs.registry import get_problem  # noqa: E402

MPI, PETSc = engine()
WORLD = MPI.COMM_WORLD
SERIAL = {}
LEVELS = {"poisson-cut": poisson_cut_level, "laplace-beltrami-cut": laplace_beltrami_cut_level}
#: the record's numbers compared (besides the unknowns and the cut's sizes)
MEASURES = {"poisson-cut": ("l2_error", "h1_error", "volume"), "laplace-beltrami-cut": ("l2_error", "h1_error", "area")}
#: a box above the sphere's: 16 cell layers at spacing 0.2, the top five without active cells
TALL = "-1.1,-1.1,-1.1,1.1,1.1,2.1"
#: the layers of each rank in the tall box: ranks without layers and ranks whose layers hold no active cell
TALL_SPLITS = {1: [16], 2: [11, 5], 3: [0, 11, 5], 4: [0, 8, 3, 5]}


def serial_record(name, spacing, box=None):
    key = (name, spacing, box)
    if key not in SERIAL:
        problem = get_problem(name)
        SERIAL[key] = problem.solve_level(spacing, **problem.resolve({"order": 2, "solver": "direct", "box": box}))
    return SERIAL[key]


def check_equal(name, rec, serial, tol=1e-10):
    assert rec["dofs"] == serial["dofs"]
    for key in ("active_tets", "pieces", "surface_triangles", "interior_faces", "background_nodes"):
        assert rec[key] == serial[key], key
    if name == "poisson-cut":
        assert rec["gamma_g"] == serial["gamma_g"] == 0.01
    for key in MEASURES[name]:
        assert abs(rec[key] - serial[key]) <= tol * abs(serial[key]), (key, rec[key], serial[key])


def run_level(comm, name, size, spacing, box=None, counts=None, tol=1e-10):
    """The level on ``comm`` (None on the ranks outside it) against the serial record."""
    serial = serial_record(name, spacing, box)
    if comm is None:
        return
    p = distributed_params(name, {"order": 2, "solver": "direct", "box": box})
    assert p["order"] == 2
    rec = LEVELS[name](spacing, **p, comm=comm, counts=counts)
    check_equal(name, rec, serial, tol)
    assert rec["ranks"] == size and rec["pc"] == "lu (mumps)"


@pytest.mark.parametrize("name", sorted(LEVELS))
@pytest.mark.parametrize("size", [1, 2, 3, 4])
def test_order2_errors_equal_serial(name, size, first_ranks):
    """Spacing 0.2 (6975 P2 unknowns of poisson-cut, 4518 of laplace-beltrami-cut) on 1-4 ranks,
    split in blocks: the serial errors to 1e-10 relative (both direct)."""
    run_level(first_ranks(size), name, size, 0.2)


@pytest.mark.parametrize("name", sorted(LEVELS))
@pytest.mark.parametrize("size", [1, 2, 3, 4])
def test_order2_with_idle_ranks(name, size, first_ranks):
    """The tall box at spacing 0.2 with ranks that own no layer or no active cell (:data:`TALL_SPLITS`)."""
    run_level(first_ranks(size), name, size, 0.2, TALL, TALL_SPLITS[size])


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(LEVELS))
@pytest.mark.parametrize("size", [1, 2, 4])
def test_order2_errors_equal_serial_fine(name, size, first_ranks):
    """As above at spacing 0.1 (42337 and 17220 unknowns); laplace-beltrami-cut's L2 error to 1e-9:
    it differs from the serial one by 6e-15 (1.3e-10 relative) on 2 ranks, by 8e-11 relative on one
    rank, whose matrix is the serial one to the order of the sums: the round-off of the two direct
    solvers (the serial factorization and MUMPS), not of the assembly."""
    run_level(first_ranks(size), name, size, 0.1, tol=1e-9 if name == "laplace-beltrami-cut" else 1e-10)


def test_poisson_order2_gamg():
    """CG with GAMG on all ranks at spacing 0.2: the serial direct errors to 1e-5 relative (CG to a
    relative residual of 1e-8; measured 4e-6, 9e-7, 2e-6 on 1, 2, 4 ranks), in at most 250
    iterations (measured 123, 122, 126: aggregation does not find the near-kernel of the P2 fictitious-domain
    system, see :func:`cutfem.solvers.multigrid.augmented_hierarchy`)."""
    serial = serial_record("poisson-cut", 0.2)
    p = distributed_params("poisson-cut", {"order": 2, "solver": "cg-amg"})
    rec = poisson_cut_level(0.2, **p, comm=WORLD)
    check_equal("poisson-cut", rec, serial, tol=1e-5)
    assert rec["pc"] == "gamg" and rec["solver_iterations"] <= 250


@pytest.mark.parametrize("name, spacing, most", [("poisson-cut", 0.2, 30), ("laplace-beltrami-cut", 0.2, 15),
                                                 pytest.param("poisson-cut", 0.1, 30, marks=pytest.mark.slow),
                                                 pytest.param("laplace-beltrami-cut", 0.1, 15, marks=pytest.mark.slow)])
def test_order2_lattice_multigrid(name, spacing, most):
    """CG with PCMG on the lattice hierarchy below the P2 unknowns (P2 -> P1 on the half-spacing
    lattice, then the Kuhn lattices; every coarse space doubled as by the serial order-2 multigrid:
    by (phi)_+ v for poisson-cut, by phi_h v and phi_h^2 v for laplace-beltrami-cut) on all ranks:
    the serial direct errors to 1e-5 relative, in at most ``most`` iterations (measured on 1, 2, 4
    ranks: poisson-cut 18, 22, 23 at 0.2 and 18, 21, 22 at 0.1, the serial multigrid 28 and 27;
    laplace-beltrami-cut 8, 9, 9 at 0.2 and at 0.1, the serial multigrid 13 and 13)."""
    serial = serial_record(name, spacing)
    p = distributed_params(name, {"order": 2, "solver": "cg-mg"})
    rec = LEVELS[name](spacing, **p, comm=WORLD)
    check_equal(name, rec, serial, tol=1e-5)
    assert rec["pc"] == "mg" and rec["solver_iterations"] <= most


@pytest.mark.skipif(not launched() or WORLD.size == 1, reason="the command line's distributed path at order 2 runs on several ranks")
def test_command_line_order2_under_mpiexec(tmp_path_factory):
    """``mpiexec -n N cutfem run poisson-cut --order 2`` (N > 1): the distributed level at order 2,
    the serial record's unknowns and errors; a problem that is P1 on several ranks is refused."""
    folder = WORLD.bcast(str(tmp_path_factory.mktemp("cli2")) if WORLD.rank == 0 else None)
    path = f"{folder}/poisson2.json"
    assert main(["run", "poisson-cut", "--order", "2", "--levels", "0.2", "--solver", "direct", "--json", path, "--quiet"]) == 0
    WORLD.Barrier()
    rec = json.load(open(path))["records"][0]
    assert rec["ranks"] == WORLD.size and rec["pc"] == "lu (mumps)"
    check_equal("poisson-cut", rec, serial_record("poisson-cut", 0.2))
    assert main(["run", "mean-curvature-cut", "--order", "2", "--levels", "0.2", "--quiet"]) == 2
