"""The geometric multigrid on PETSc: cutfem's lattice prolongations, row by row on the ranks that own
them, and PETSc's PCMG (docs/math.md §19), for the surface systems, the bulk ones and the blocks of
the Stokes saddle system.

Why
---
The TraceFEM systems A_Gamma + M + tau_F J_F (laplace-beltrami-cut) and M + tau_F J_F
(mean-curvature-cut) have two near-kernels that algebraic multigrid does not find from the matrix:
the locally linear functions (J_F sees them through O(h) gradient jumps, a fourth-order character
along the surface) and the normally linear functions phi_h g, g smooth, which vanish on S_h and
which only J_F sees.  Aggregation (GAMG) and classical AMG (hypre BoomerAMG) both need about twice
the CG iterations at each halving of h on them.  The serial multigrid's hierarchy
(:mod:`cutfem.solvers.multigrid`) represents both on every level: the nested Kuhn lattices
reproduce the linear functions, and each coarse space holds the products phi_h v beside v
(:func:`~cutfem.solvers.multigrid.augmented_hierarchy`).  Here that hierarchy is built on the
ranks and handed to PETSc, which does the Galerkin products, the smoothing and the coarse solve.

Distributed hierarchy
---------------------
Level l is a set of nodes of the lattice 2^l h Z^3 (level 0: the active background nodes; of a P2
field the P2 nodes on the lattice h/2 Z^3, level l >= 1 then on 2^(l-1) h Z^3) with one
or two copies each (v and phi_h v; k + 1 for k augmenting vectors, phi_h and phi_h^2 of a P2
surface field); node I of level l is owned by the owner of the background node
layer 2^l I_z (:meth:`~cutfem.distributed.partition.Slabs.node_owner`'s rule), so a rank's rows of
every level are a slab of the lattice and level 0 is the system's own numbering.  Each rank builds
the rows of P_l that it owns with :func:`~cutfem.solvers.multigrid.kuhn_prolongation` (weight 1 on
the coarse node I/2 or 1/2 on the ends of the coarse Kuhn edge that I halves; copy c to copy c,
and at the first level also weight phi_h(I) times the Kuhn weight to copy 1), sends the coarse
nodes it uses to their owners, which number the union of what they receive in lexicographic order
(a block of consecutive numbers per rank, so the coarse vectors are laid out as PETSc wants), and
receives their numbers: two all-to-all exchanges a level.  Entries of weight zero (phi_h(I) = 0)
are not stored, so no coarse function has a zero prolongation.  Levels are added while the coarse
level has at most 0.9 times the unknowns of the finer one and the finer one more than
``coarse_size``.  The rows and their weights do not depend on the number of ranks: the
hierarchy is the serial one.

Fields of several unknowns
--------------------------
The bulk fields take the plain lattices, and a field of c unknowns a node numbered together (a
velocity's 3 components, keyed ``node * 4 + field`` so that a node's components are consecutive
in its split of the Stokes system) the scalar prolongation per component, P kron I_c, which is
the serial block prolongation (:func:`~cutfem.solvers.multigrid.multigrid_hierarchy` of a
:class:`~cutfem.fem.spaces.VectorSpace`) in the node-major order.  Unknowns of no node (the
pressure's mean-value multiplier, last on the last rank) stay on every level as themselves.

Cycle
-----
A V-cycle of PCMG with the coarse operators P^T A P (MatPtAP), smoothed by two steps of
Chebyshev with SOR on each level (PETSc's default smoother; SOR is local to each rank, so the
preconditioner depends on the partition slightly); the coarsest level (at most ``coarse_size``
unknowns) is solved by a pseudo-inverse (PCSVD): the doubled coarse spaces can be linearly
dependent there (two coarse nodes seen through one fine node at the edge of the band), which
makes P^T A P singular, harmlessly, since its null vectors are those of P.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..solvers.multigrid import kuhn_prolongation
from .launch import engine

__all__ = ["lattice_prolongations", "set_multigrid", "COARSE_SIZE"]

#: the coarsest level has at most this many unknowns (the serial augmented hierarchy's, problems/laplace_beltrami.py)
COARSE_SIZE = 400


def lattice_prolongations(comm, slabs, nodes, augment=None, coarse_size: int = COARSE_SIZE, max_levels: int = 20,
                          components: int = 1, constants: int = 0, order: int = 1) -> list:
    """The prolongations P_0, P_1, ... (PETSc MPIAIJ, finest first) of the Kuhn lattices below the
    unknowns ``nodes`` of this rank (its owned unknowns' global background node ids, or at
    ``order`` 2 their P2 nodes ``8 v + c``, increasing: the rows of the system it owns, in order),
    on the structured box of ``slabs``.  A P2 node, the midpoint of the edge {v, w}
    (:meth:`~cutfem.distributed.partition.Slabs.p2_ends`; w = v for a vertex), is the node
    ijk(v) + ijk(w) of the lattice of half the spacing (as :func:`~cutfem.solvers.multigrid.lattice_indices`
    numbers a serial P2 space), so the first prolongation is the embedding of P1 in P2.  ``augment``:
    nodal values w at ``nodes`` (phi_h of a surface field, (phi)_+ of a P2 bulk field), doubling
    every coarse space with w v (see the module docstring), or k columns of them (phi_h and phi_h^2
    of a P2 surface field: k + 1 copies), or None for the plain lattices.  ``components``: the
    unknowns of a node, numbered together (a velocity's 3 components, row 3 i + c the component c of
    node i): the prolongation of each level is the scalar one applied to each component, P kron I_c,
    and the coarsest level has at most ``coarse_size`` unknowns.  ``constants``: unknowns of no node
    after the last rank's rows (a multiplier, :class:`~cutfem.distributed.system.GlobalNumbering`),
    kept on every level (an identity row and column at the end of the last rank's block)."""
    _, PETSc = engine()
    box = slabs.box
    nz = int(box.cells[2])
    per = int(box.node_shape[0] * box.node_shape[1])
    nodes = np.asarray(nodes, dtype=np.int64)
    ijk = box.node_index(nodes) if order == 1 else sum(box.node_index(end) for end in slabs.p2_ends(nodes))
    fine = 2 if order == 2 else 1  # level 0's lattice: spacing h / fine
    m = 2 if augment is None or np.ndim(augment) == 1 else 1 + np.shape(augment)[1]  # copies of a coarse node
    copies = np.zeros(len(nodes), dtype=np.int64)  # the rows: lattice nodes (sorted lexicographically) and their copy
    n_global = int(comm.allreduce(len(nodes)))
    out = []
    c = int(components)
    for level in range(max_levels):
        if c * n_global <= coarse_size:
            break
        rows, cols, vals, cijk = _local_rows(ijk, copies, augment if level == 0 else None, m)
        # the coarse keys: lexicographic number of the coarse node (a box large enough for every
        # level) times m plus the copy; the owner: the owner of its node layer
        dims = fine * np.array(box.node_shape, dtype=np.int64) // 2 ** (level + 1) + 2
        code = cijk[:, 0] + dims[0] * (cijk[:, 1] + dims[1] * cijk[:, 2])
        keys = m * code[cols // m] + cols % m
        scale = 2 ** (level + 1) // fine  # coarse node K lies on the background node layer scale K_z
        owner_of = lambda k: slabs.node_owner(np.minimum(scale * (k // m // (dims[0] * dims[1])), nz) * per)  # noqa: E731
        owned, first, nc_global, numbers = _number_union(comm, keys, owner_of)
        if nc_global >= 0.9 * n_global:
            break
        local = sp.csr_matrix((vals, (rows, numbers)), shape=(len(ijk), nc_global))
        local.sum_duplicates()
        if c > 1:
            local = sp.kron(local, sp.identity(c), format="csr")
        k = constants if comm.rank == comm.size - 1 else 0  # the last rank's rows end with the constants
        cols = c * nc_global + constants
        local = sp.vstack([sp.csr_matrix((local.data, local.indices, local.indptr), shape=(local.shape[0], cols)),
                           sp.csr_matrix((np.ones(k), (np.arange(k), c * nc_global + np.arange(k))), shape=(k, cols))], format="csr")
        local.sort_indices()
        P = PETSc.Mat().createAIJ(((c * len(ijk) + k, c * n_global + constants), (c * len(owned) + k, cols)),
                                  csr=(local.indptr.astype(PETSc.IntType), local.indices.astype(PETSc.IntType), local.data), comm=comm)
        P.assemble()
        out.append(P)
        code = owned // m
        ijk = np.stack([code % dims[0], (code // dims[0]) % dims[1], code // (dims[0] * dims[1])], axis=1)
        copies, n_global = owned % m, nc_global
    return out


def _local_rows(ijk, copies, augment, m: int = 2):
    """The entries (row, local column, weight) of this rank's rows of a prolongation, and the
    coarse lattice nodes (mc, 3) the local columns m j + c name (node j, copy c of m)."""
    if len(ijk) == 0:
        return (np.zeros(0, np.int64),) * 2 + (np.zeros(0), np.zeros((0, 3), np.int64))
    code = ijk[:, 0] + (ijk[:, 0].max() + 1) * (ijk[:, 1] + (ijk[:, 1].max() + 1) * ijk[:, 2])
    _, first, which = np.unique(code, return_index=True, return_inverse=True)  # a node's copies share its Kuhn weights
    nodes, which = ijk[first], which.reshape(-1)
    P, cijk = kuhn_prolongation(nodes)
    counts = np.diff(P.indptr)[which]
    rows = np.repeat(np.arange(len(ijk)), counts)
    starts = np.repeat(P.indptr[:-1][which] - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    at = starts + np.arange(len(rows))
    cols, vals = m * P.indices[at].astype(np.int64) + copies[rows], P.data[at]
    if augment is not None:  # the first level: copy 0 gets v, copy j gets w_j v
        ws = np.asarray(augment, dtype=float).reshape(len(ijk), -1)
        parts = [(rows, cols, vals)]
        for j in range(ws.shape[1]):
            w = ws[rows, j] * vals
            keep = w != 0.0
            parts.append((rows[keep], cols[keep] + 1 + j, w[keep]))
        rows, cols, vals = (np.concatenate(a) for a in zip(*parts))
    return rows, cols, vals, cijk


def _number_union(comm, keys, owner_of):
    """Number the union over the ranks of ``keys`` (any order, repeats allowed), each key numbered
    by its owner (``owner_of(keys)``; owners' keys must increase with the owner): the keys a rank
    owns, in increasing order, get consecutive numbers after the lower ranks'.  Returns (this
    rank's owned keys, its first number, the number of keys, the numbers of ``keys``)."""
    MPI, _ = engine()
    asked, inverse = np.unique(keys, return_inverse=True)
    owners = owner_of(asked)
    send = np.bincount(owners, minlength=comm.size).astype(np.int64)
    recv = np.empty_like(send)
    comm.Alltoall(send, recv)
    sdispl, rdispl = _displacements(send), _displacements(recv)
    got = np.empty(int(recv.sum()), dtype=np.int64)
    comm.Alltoallv([asked, (send, sdispl), MPI.INT64_T], [got, (recv, rdispl), MPI.INT64_T])
    owned = np.unique(got)
    first = int(comm.exscan(len(owned)) or 0) if comm.size > 1 else 0
    n_global = int(comm.allreduce(len(owned)))
    answer = (first + np.searchsorted(owned, got)).astype(np.int64)
    numbers = np.empty(len(asked), dtype=np.int64)
    comm.Alltoallv([answer, (recv, rdispl), MPI.INT64_T], [numbers, (send, sdispl), MPI.INT64_T])
    return owned, first, n_global, numbers[inverse.reshape(-1)]


def _displacements(counts) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)


def set_multigrid(ksp, A, prolongations) -> list:
    """Make the PC of ``ksp`` (operators ``A``) a PCMG V-cycle on ``prolongations`` (finest
    first): Galerkin coarse operators, Chebyshev with SOR on each level, a pseudo-inverse on the
    coarsest.  Returns the coarse operators (the caller destroys them with the KSP)."""
    _, PETSc = engine()
    pc = ksp.getPC()
    pc.setType("mg")
    L = len(prolongations) + 1
    pc.setMGLevels(L)
    pc.setMGCycleType(PETSc.PC.MGCycleType.V)
    operators, Al = [], A
    for k, P in enumerate(prolongations):  # PCMG's level L - 1 is the finest, level 0 the coarsest
        pc.setMGInterpolation(L - 1 - k, P)
        Al = Al.PtAP(P)
        Al.setOption(PETSc.Mat.Option.SPD, True)
        # point SOR: with inodes PETSc's SOR inverts the 2 x 2 blocks of a node's two copies v and
        # phi_h v, nearly dependent where phi_h varies little over the node's support (a zero pivot)
        Al.setOption(PETSc.Mat.Option.USE_INODES, False)
        operators.append(Al)
        pc.getMGSmoother(L - 2 - k).setOperators(Al)
    for level in range(1, L):
        smoother = pc.getMGSmoother(level)
        smoother.setType("chebyshev")
        smoother.getPC().setType("sor")
        smoother.setTolerances(max_it=2)
    coarse = pc.getMGCoarseSolve()
    coarse.setType("preonly")
    coarse.getPC().setType("svd")
    return operators
