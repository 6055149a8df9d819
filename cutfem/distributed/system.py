"""Global numbering of the unknowns, and the linear system on PETSc (MPIAIJ, Vec, KSP).

Numbering
---------
The serial P1 space of a cut numbers its unknowns by increasing background node id
(:class:`~cutfem.fem.spaces.CutSpace`).  Distributed, a node is owned by the rank the partition
names (``node_owner``: the owner of its cell layer for slabs, of its lowest-id cell for the cell
partition), which numbers the active nodes it owns in increasing id: the ones its own pieces
touch and the ones other ranks ask of it (a node may be active through a tet the owner does not
hold), so a node's number is its owner's offset (an exclusive scan of the counts) plus its rank
among the owner's nodes, and the numbers of the other nodes a rank touches come from their owners
in one all-to-all exchange (:class:`GlobalNumbering`).  Slabs own consecutive blocks of node ids,
so their numbers are the serial ones and a distributed vector is the serial one entry by entry; the
cell partition's are a permutation of them, the serial order within each rank.  A P2 field's
unknowns are keyed by their P2 node ``8 v + c`` (``slots`` 8: the node v and the Kuhn edges above
it), owned by v's owner: the serial count, in a permutation of the serial order.

System
------
Each rank adds the matrices of its local spaces as COO triples in global numbers
(:meth:`LinearSystem.add_matrix`), and its local load vectors (:meth:`LinearSystem.add_vector`);
the triples of rows another rank owns travel to it, and each rank's rows go to PETSc as exact CSR
arrays of an MPIAIJ matrix (petsc4py 3.18 has no COO assembly).  The solve is PETSc's, to a
relative residual of 1e-8 for SPD systems: CG preconditioned by PCMG on cutfem's lattice
prolongations ("cg-mg", :mod:`~cutfem.distributed.preconditioners`; for a surface field each coarse
space doubled by phi_h v), by GAMG (smoothed aggregation, "cg-amg"), or an LU factorization by
MUMPS ("direct").  ``solver="auto"`` follows the serial ``solve``: with the lattice hierarchy (one
field on the structured box) direct up to :data:`~cutfem.solvers.solve.DIRECT_LIMIT` unknowns and
cg-mg above; without it (product spaces) direct up to
:data:`~cutfem.solvers.solve.DIRECT_LIMIT_NO_MG_BULK` unknowns of a bulk field
(:data:`~cutfem.solvers.solve.DIRECT_LIMIT_NO_MG` of a surface field) and GAMG above.
GAMG and hypre's BoomerAMG need about twice the iterations at each halving of h on the TraceFEM
systems, whose near-kernel (the functions phi_h g that vanish on S_h, and the locally linear ones
that J_F hardly sees) aggregation does not find; the lattice hierarchy holds both on every level,
and CG then takes 8-9 iterations (laplace-beltrami-cut) or 9-17 (mean-curvature-cut) from 766 to
290 thousand unknowns, on 1 and 2 ranks (docs/math.md §19).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..solvers.krylov import DEFAULT_TOL
from ..solvers.solve import DIRECT_LIMIT, DIRECT_LIMIT_NO_MG, DIRECT_LIMIT_NO_MG_BULK
from .launch import engine
from .preconditioners import set_multigrid

__all__ = ["GlobalNumbering", "LinearSystem", "DISTRIBUTED_SOLVERS"]

#: solver names of the problems (problems/common.py SOLVERS) -> (KSP type, PC type); "auto" chooses by size
DISTRIBUTED_SOLVERS = {"direct": ("preonly", "lu"), "cg-mg": ("cg", "mg"), "cg-amg": ("cg", "gamg"), "cg-jacobi": ("cg", "jacobi")}


class GlobalNumbering:
    """The global numbers of the unknowns one rank touches, given by their keys ``node * fields +
    field`` (global background node ids; any order, repeats allowed; ``fields`` > 1 for a product
    space), each owned by the owner of its node in ``partition`` (``partition.node_owner``).  A
    rank numbers its owned keys (its own and those asked of it) in increasing order.  ``first`` and
    ``n_owned``: this rank's block of numbers; ``n_global`` the number of unknowns.  ``constants``:
    unknowns of no node (a multiplier's), keyed -1, -2, ..., numbered after every node's unknowns
    and owned by the last rank (its block ends the numbering).  ``slots``: the units a node has (a
    P2 field's 8, :data:`~cutfem.distributed.assembly.P2_SLOTS`: the key's unit is ``node * slots +
    slot``), all owned by the node's owner."""

    def __init__(self, comm, partition, rank: int, keys, fields: int = 1, constants: int = 0, slots: int = 1):
        MPI, _ = engine()
        keys = np.unique(np.asarray(keys, dtype=np.int64))
        if len(keys) and keys[0] < -constants:
            raise ValueError(f"key {keys[0]} is below the {constants} constants' keys -1 ... -{constants}")
        constant_keys, keys = keys[keys < 0], keys[keys >= 0]
        owners = partition.node_owner(keys // fields // slots)
        mine = owners == rank
        others = keys[~mine]
        # the other keys go to their owners (grouped by owner), which number them with their own
        order = np.argsort(owners[~mine], kind="stable")
        others, owners = others[order], owners[~mine][order]
        send = np.bincount(owners, minlength=comm.size).astype(np.int64)
        recv = np.empty_like(send)
        comm.Alltoall(send, recv)
        asked = np.empty(int(recv.sum()), dtype=np.int64)
        sdispl, rdispl = _displacements(send), _displacements(recv)
        comm.Alltoallv([others, (send, sdispl), MPI.INT64_T], [asked, (recv, rdispl), MPI.INT64_T])
        owned = np.union1d(keys[mine], asked)
        self.fields = fields
        self.n_owned = len(owned)
        self.first = int(comm.exscan(self.n_owned) or 0) if comm.size > 1 else 0
        self.n_global = int(comm.allreduce(self.n_owned))
        answer = (self.first + np.searchsorted(owned, asked)).astype(np.int64)
        got = np.empty(len(others), dtype=np.int64)
        comm.Alltoallv([answer, (recv, rdispl), MPI.INT64_T], [got, (send, sdispl), MPI.INT64_T])
        self.keys = np.concatenate([constant_keys, keys])
        self.owned_keys = owned
        self.numbers = np.empty(len(keys), dtype=np.int64)
        self.numbers[mine] = self.first + np.searchsorted(owned, keys[mine])
        self.numbers[np.flatnonzero(~mine)[order]] = got
        self.numbers = np.concatenate([self.n_global - 1 - constant_keys, self.numbers])  # key -1 -> the first after the nodes'
        self.n_owned += constants if comm.rank == comm.size - 1 else 0
        self.n_global += constants

    def __call__(self, keys) -> np.ndarray:
        """The global numbers of keys (all among the keys given)."""
        return self.numbers[np.searchsorted(self.keys, np.asarray(keys, dtype=np.int64))]


def _displacements(counts) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)


class LinearSystem:
    """A matrix and a right-hand side assembled on PETSc from each rank's local pieces."""

    def __init__(self, comm, numbering: GlobalNumbering):
        self.comm, self.numbering = comm, numbering
        self._rows, self._cols, self._vals = [], [], []
        self._vec_rows, self._vec_vals = [], []
        self._given = False

    def add_matrix(self, local, dofs) -> None:
        """Add a local matrix (scipy sparse, n x n) whose row/column i is the unknown ``dofs[i]``."""
        coo = local.tocoo()
        dofs = np.asarray(dofs, dtype=np.int64)
        self._rows.append(dofs[coo.row])
        self._cols.append(dofs[coo.col])
        self._vals.append(np.asarray(coo.data, dtype=float))

    def add_vector(self, local, dofs) -> None:
        """Add a local load (n,) or loads (n, k) (k right-hand sides, one system matrix)."""
        self._vec_rows.append(np.asarray(dofs, dtype=np.int64))
        local = np.asarray(local, dtype=float)
        self._vec_vals.append(local.reshape(len(local), -1))


    def petsc(self):
        """(A, [b, ...]): the MPIAIJ matrix and the right-hand side Vecs (one per column of the
        loads).  The triples and the load
        entries of rows that other ranks own are sent to them first (:meth:`_to_owners`); each rank
        then sums its rows' triples into CSR (scipy sums duplicates) and hands PETSc exact CSR
        arrays (``MatCreateMPIAIJWithArrays``: preallocated, no stash)."""
        MPI, PETSc = engine()
        n, N = self.numbering.n_owned, self.numbering.n_global
        if self._given:
            raise RuntimeError("this system's triples went to PETSc already (petsc() releases them): assemble a new system")
        # the triples are the largest arrays of a rank (24 bytes an entry): each list is released as it
        # is joined and each joined array as it is exchanged, so that at most one extra copy of one of
        # them is alive at a time
        triples = []
        for name, kind in (("_rows", np.int64), ("_cols", np.int64), ("_vals", float)):
            arrays = getattr(self, name)
            setattr(self, name, [])
            triples.append(arrays[0] if len(arrays) == 1 else np.concatenate(arrays) if arrays else np.zeros(0, kind))
            del arrays
        self._given = True
        rows, cols, vals = self._to_owners(triples)
        rows -= self.numbering.first
        local = sp.csr_matrix((vals, (rows, cols)), shape=(n, N))
        del rows, cols, vals
        local.sum_duplicates()
        local.sort_indices()
        A = PETSc.Mat().createAIJ(((n, N), (n, N)), csr=(local.indptr.astype(PETSc.IntType, copy=False),
                                                         local.indices.astype(PETSc.IntType, copy=False), local.data),
                                  comm=self.comm)
        del local
        A.assemble()
        # the number of loads, agreed by all ranks: one without loads would exchange one column and the others k
        k = self.comm.allreduce(max((v.shape[1] for v in self._vec_vals), default=1), op=MPI.MAX)
        vrows = np.concatenate(self._vec_rows) if self._vec_rows else np.zeros(0, np.int64)
        vvals = np.concatenate(self._vec_vals) if self._vec_vals else np.zeros((0, k))
        vrows, *columns = self._to_owners([vrows, *vvals.T])
        first = self.numbering.first
        loads = []
        for column in columns:
            b = A.createVecLeft()
            b.setArray(np.bincount(vrows - first, weights=column, minlength=n) if n else np.zeros(0))
            loads.append(b)
        return A, loads

    def _to_owners(self, arrays):
        """The entries of the rows this rank owns, received from every rank (one all-to-all
        exchange; each row owned by the rank whose block of numbers holds it): ``arrays`` the rows
        and the arrays beside them, a list that is emptied as each array is sent (the caller holds
        no other reference, so each is freed once its copy in the owners' order exists)."""
        MPI, _ = engine()
        comm = self.comm
        firsts = np.array(comm.allgather(self.numbering.first), dtype=np.int64)
        owner = np.searchsorted(firsts, arrays[0], side="right") - 1
        order = np.argsort(owner, kind="stable")
        send = np.bincount(owner, minlength=comm.size).astype(np.int64)
        del owner
        recv = np.empty_like(send)
        comm.Alltoall(send, recv)
        sdispl, rdispl = _displacements(send), _displacements(recv)
        out = []
        while arrays:
            a = np.ascontiguousarray(arrays.pop(0)[order])
            got = np.empty(int(recv.sum()), dtype=a.dtype)
            kind = MPI.INT64_T if a.dtype == np.int64 else MPI.DOUBLE
            comm.Alltoallv([a, (send, sdispl), kind], [got, (recv, rdispl), kind])
            del a
            out.append(got)
        return out

    def solve(self, A, loads, solver: str = "auto", tol: float = DEFAULT_TOL, bulk: bool = True, hierarchy=None):
        """``([x, ...], info)``: the solutions of A x = b for each load Vec by PETSc's KSP (one
        setup for all) and what solved them (``engine``, ``ksp``, ``pc``, ``iterations`` (the most
        of any load), ``residual`` (the largest relative one), ``ranks``).  ``tol``: the relative
        residual of CG; ``bulk``: the unknowns fill a volume (the size up to which "auto" is
        direct); ``hierarchy``: None, or a function that returns the lattice prolongations
        (:func:`~cutfem.distributed.preconditioners.lattice_prolongations`), called for "cg-mg" only.
        A row without any term (a zero diagonal) raises ValueError; a KSP that
        does not converge RuntimeError with PETSc's reason."""
        _, PETSc = engine()
        N = self.numbering.n_global
        if solver == "auto":
            if hierarchy is not None:
                solver = "direct" if N <= DIRECT_LIMIT else "cg-mg"
            else:
                solver = "direct" if N <= (DIRECT_LIMIT_NO_MG_BULK if bulk else DIRECT_LIMIT_NO_MG) else "cg-amg"
        if solver not in DISTRIBUTED_SOLVERS:
            raise ValueError(f"solver={solver!r} is not available on PETSc; distributed runs take "
                             f"{', '.join(['auto', *DISTRIBUTED_SOLVERS])}")
        if solver == "cg-mg" and hierarchy is None:
            raise ValueError("solver='cg-mg' needs the lattice hierarchy of a single field on a structured box, which this "
                             "problem does not give on PETSc: use 'cg-amg' or 'direct'")
        diagonal = A.getDiagonal()
        if diagonal.min()[1] <= 0.0:
            raise ValueError("the system has a row with no positive diagonal entry (an unknown that no term sees, e.g. S_h "
                             "along faces of the grid): run this level on one rank, which pins such unknowns")
        diagonal.destroy()
        ksp_type, pc_type = DISTRIBUTED_SOLVERS[solver]
        ksp = PETSc.KSP().create(comm=self.comm)
        ksp.setOperators(A)
        ksp.setType(ksp_type)
        pc = ksp.getPC()
        pc.setType(pc_type)
        made = []  # the multigrid's prolongations and coarse operators
        if pc_type == "mg":
            made = hierarchy()
            made += set_multigrid(ksp, A, made)
        if pc_type == "lu":
            pc.setFactorSolverType("mumps")
        else:
            A.setOption(PETSc.Mat.Option.SPD, True)
            ksp.setTolerances(rtol=tol, atol=0.0, max_it=10_000)
            ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
        ksp.setFromOptions()  # PETSC_OPTIONS may change any of it
        xs, iterations, residual = [], 0, 0.0
        for b in loads:
            x = A.createVecRight()
            ksp.solve(b, x)
            reason = ksp.getConvergedReason()
            if reason < 0:
                raise RuntimeError(f"PETSc's KSP {ksp.getType()} with PC {ksp.getPC().getType()} did not converge: reason "
                                   f"{reason} after {ksp.getIterationNumber()} iterations (see KSPConvergedReason)")
            r = b.duplicate()
            A.mult(x, r)
            r.aypx(-1.0, b)
            bn = b.norm()
            residual = max(residual, float(r.norm() / bn) if bn > 0 else float(r.norm()))
            iterations = max(iterations, int(ksp.getIterationNumber()))
            r.destroy()
            xs.append(x)
        pc_name = f"lu ({pc.getFactorSolverType()})" if pc_type == "lu" else pc.getType()
        info = {"engine": f"PETSc {'.'.join(map(str, PETSc.Sys.getVersion()))}", "ksp": ksp.getType(), "pc": pc_name,
                "iterations": iterations, "residual": residual, "ranks": int(self.comm.size)}
        for obj in (ksp, *made):
            obj.destroy()
        return xs, info

    def gather(self, x, dofs) -> np.ndarray:
        """The entries ``dofs`` (global numbers, any of them) of a distributed Vec on this rank."""
        _, PETSc = engine()
        dofs = np.asarray(dofs, dtype=PETSc.IntType)
        out = PETSc.Vec().createSeq(len(dofs), comm=PETSc.COMM_SELF)
        index = PETSc.IS().createGeneral(dofs, comm=PETSc.COMM_SELF)
        scatter = PETSc.Scatter().create(x, index, out, None)
        scatter.scatter(x, out, PETSc.InsertMode.INSERT_VALUES, PETSc.ScatterMode.FORWARD)
        values = out.getArray().copy()
        for obj in (scatter, index, out):
            obj.destroy()
        return values
