"""The multigrid of the distributed saddle solve (docs/math.md §19): the lattice prolongations of a
vector field and of a pressure with its multiplier, and MINRES's iterations with PCMG on both
blocks of stokes-cut's field split, on 1 and 2 ranks (run under mpiexec like test_distributed_mpi)."""

import pytest
import scipy.sparse as sp

pytest.importorskip("mpi4py")
pytest.importorskip("petsc4py")

from cutfem.distributed import distributed_params  # noqa: E402
from cutfem.distributed.launch import engine  # noqa: E402
from cutfem.distributed.partition import slab_partition  # noqa: E402
from cutfem.distributed.preconditioners import lattice_prolongations  # noqa: E402
from cutfem.distributed.stokes import stokes_cut_level  # noqa: E402
from cutfem.fem.spaces import CutSpace  # noqa: E402
from cutfem.geometry.cut import cut_mesh  # noqa: E402
from cutfem.geometry.markers import NEG  # noqa: E402
from cutfem.problems.common import background_for, levelset_for  # noqa: E402

MPI, PETSc = engine()
WORLD = MPI.COMM_WORLD

#: MINRES's iterations to 1e-12 (the preconditioned residual) with PCMG on the velocity and on the
#: pressure's Schur approximation: measured 51 and 54 at spacings 0.2 and 0.1 on 1 rank, 51 and 56
#: on 2 (GAMG and Chebyshev-Jacobi took 151 and 153 on 1 rank)
BOUND = 62


def local_rows(P):
    """This rank's rows of a PETSc matrix, as a scipy CSR matrix with the global columns."""
    indptr, indices, data = P.getValuesCSR()
    return sp.csr_matrix((data, indices, indptr), shape=(P.getLocalSize()[0], P.getSize()[1]))


def same(X, Y) -> bool:
    """Two sparse matrices equal entry by entry."""
    d = sp.csr_matrix(X - Y)
    d.eliminate_zeros()
    return d.nnz == 0


def test_vector_and_constant_prolongations_are_the_scalar_ones_per_component():
    """On the ball at spacing 0.1, every level: the prolongation of 3 components numbered together is
    P kron I_3 of the scalar one, row by row on each rank, and a constant (the multiplier) appended
    to the last rank's rows is an identity row and column at the end of its block."""
    phi = levelset_for("sphere")
    bg = background_for(phi, 0.1, "structured", None)
    V = CutSpace(cut_mesh(bg, phi), NEG)
    slabs = slab_partition(bg, WORLD.size)
    nodes = V.node_ids[slabs.node_owner(V.node_ids) == WORLD.rank]
    scalar = lattice_prolongations(WORLD, slabs, nodes)
    vector = lattice_prolongations(WORLD, slabs, nodes, components=3, coarse_size=3 * 400)
    pressure = lattice_prolongations(WORLD, slabs, nodes, constants=1)
    assert len(scalar) == len(vector) == len(pressure) >= 2
    last = WORLD.rank == WORLD.size - 1
    for S, B, C in zip(scalar, vector, pressure):
        s = local_rows(S)
        assert B.getSize() == (3 * S.getSize()[0], 3 * S.getSize()[1])
        assert same(local_rows(B), sp.kron(s, sp.identity(3)))
        c = local_rows(C)
        assert C.getSize() == (S.getSize()[0] + 1, S.getSize()[1] + 1) and c.shape[0] == s.shape[0] + last
        assert same(c[: s.shape[0], : s.shape[1]], s) and c[: s.shape[0], s.shape[1]:].nnz == 0
        if last:
            assert c[-1].indices.tolist() == [S.getSize()[1]] and c[-1].data.tolist() == [1.0]
    for P in scalar + vector + pressure:
        P.destroy()


@pytest.mark.parametrize("size", [1, 2])
def test_stokes_minres_iterations_are_bounded_with_the_lattice_multigrid(size, first_ranks):
    """stokes-cut on the ball at spacings 0.2 and 0.1 (4 041 and 22 997 unknowns): MINRES with PCMG
    on both blocks needs at most :data:`BOUND` iterations, and at 0.1 its errors are MUMPS's to 1e-10."""
    comm = first_ranks(size)
    if comm is None:
        return
    for spacing in (0.2, 0.1):
        rec = stokes_cut_level(spacing, **distributed_params("stokes-cut", {"solver": "minres"}), comm=comm)
        assert rec["pc"] == "fieldsplit (mg, mg)" and rec["residual"] < 1e-10
        assert rec["solver_iterations"] <= BOUND, (spacing, rec["solver_iterations"])
    direct = stokes_cut_level(0.1, **distributed_params("stokes-cut", {"solver": "direct"}), comm=comm)
    for key in ("l2_error_velocity", "h1_error_velocity", "l2_error_pressure"):
        assert abs(rec[key] - direct[key]) <= 1e-10 * direct[key], (key, rec[key], direct[key])


class options:
    """PETSc's options ``given`` (name: value) while inside."""

    def __init__(self, **given):
        self.given = given

    def __enter__(self):
        for name, value in self.given.items():
            PETSc.Options()[name] = value

    def __exit__(self, *exc):
        for name in self.given:
            PETSc.Options().delValue(name)


@pytest.mark.parametrize("given, pc", [({"fieldsplit_primal_pc_type": "gamg"}, "fieldsplit (gamg, mg)"),
                                       ({"fieldsplit_primal_pc_type": "gamg", "fieldsplit_constraint_pc_type": "jacobi"},
                                        "fieldsplit (gamg, chebyshev+jacobi)")])
def test_gamg_and_chebyshev_jacobi_stay_selectable(given, pc):
    """PETSc's options take GAMG for the velocity (the pressure keeps its PCMG), or also the
    Chebyshev-Jacobi of the pressure (the split of a background without the lattice): the same
    errors as PCMG's at spacing 0.2 to 1e-10, with more iterations."""
    p = distributed_params("stokes-cut", {"solver": "minres"})
    mg = stokes_cut_level(0.2, **p)
    with options(**given):
        other = stokes_cut_level(0.2, **p)
    assert other["pc"] == pc and mg["pc"] == "fieldsplit (mg, mg)"
    assert other["solver_iterations"] > mg["solver_iterations"]
    for key in ("l2_error_velocity", "h1_error_velocity", "l2_error_pressure"):
        assert abs(other[key] - mg[key]) <= 1e-10 * mg[key], key
