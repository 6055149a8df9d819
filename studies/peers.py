"""Side by side with a peer: ngsxfem (NGSolve + xfem) on the identical cut mean curvature problem.

The cut problem (docs/math.md §3, §6.3)
-------------------------------
Both codes solve, on the paper's box [-1.6,1.6]^2 x [-0.6,0.6] with the torus R = 1, r = 1/2:

* the same tetrahedra: the NGSolve mesh is built from cutfem's :class:`~cutfem.geometry.mesh.StructuredBox`
  ``points``/``tets`` (six Kuhn tets per cube) with ``netgen.meshing.Mesh.AddPoints/AddElements``:
  point k of cutfem = vertex k of NGSolve, tet k = element k.  Netgen's tetrahedra are negatively
  oriented in the usual sense (checked on ``netgen.csg.unit_cube``: all its tets have det < 0), so
  by default vertices 1 and 2 of each tet are swapped; the boundary triangles of the box (found
  among the tets of the boundary cells, not from the whole face topology) are added, outward, in
  one face descriptor.  Volume integrals, the facet normal (outward either way, and it enters
  squared) and so the discrete problem do not depend on the orientation;
* the same P1 level set: the nodal values of rho computed and snapped exactly as cutfem's cut does
  (``cutfem.geometry.cut.nodal_values`` + the zero rule's snap) are copied into an order-1 ``H1``
  GridFunction (its dofs are the vertices);
* the same active mesh and form: ``CutInfo(mesh, lset)``, the ``IF`` elements, the H1 space with
  ``dgjumps=True`` (without it the facet couplings are missing from the sparsity pattern and
  assembly stops with "illegal dnums") compressed to the dofs of the IF elements,
  ``RestrictedBilinearForm`` with the mass (H, v) on ``dCut(lset, IF)`` and the ghost penalty
  tau_F ([n_F.grad u], [n_F.grad v]) on ``dx(skeleton=True)`` over the facets between two IF
  elements (``GetFacetsWithNeighborTypes(..., bnd_val_a=False, bnd_val_b=False, use_and=True)``),
  jump ``grad u - grad u.Other()`` dotted with ``specialcf.normal(3)``, tau_F = 0.1, no power of h;
  right-hand side ((P_h grad v)_k, 1)_{S_h} = (grad_{S_h} x_k, grad_{S_h} v)_{S_h} with
  P_h = I - n_h n_h^T, n_h = grad phi_h / |grad phi_h|;
* the same error: the L2(S_h) norm of H_h - H^e, H^e = (k1 + k2)(p(x)) n(p(x)) written as an
  NGSolve CoefficientFunction, by ``dCut`` quadrature of order 4 (cutfem: degree 4 on the triangles
  of S_h).

Each record checks that both codes have the same number of active tets, ghost faces and unknowns
(``same_problem``).  cutfem runs through ``cutfem.run("mean-curvature-cut", levels=[s], tau_f=0.1,
solver="direct")``, so that both codes solve with a sparse direct factorization.

What the remaining difference is
--------------------------------
With netgen's vertex order the errors differ by 2.4e-7 (relative) at spacing 0.2 and 1e-8 or less
below: both codes split a quadrilateral piece of S_h into two triangles, along diagonals that
depend on the vertex order of the tet, and a degree-4 rule on two different triangulations of the
same planar quadrilateral gives different values for a non-polynomial integrand.  Measured at
spacing 0.2: the difference is 2.4e-7, 2.1e-9, 6.3e-11 at quadrature degree 4, 6, 8; and with the
tets handed to NGSolve in cutfem's own vertex order (``orientation="cutfem"``) it is 5e-15 at
degree 4.  The study repeats the ngsxfem solve in cutfem's vertex order at spacings >= 0.05
(``same_vertex_order``).

Zero nodal values
-----------------
At spacing 0.1 and finer, nodes of the paper's box lie exactly on the torus (after cutfem's snap:
96 nodes at 0.1).  cutfem counts them as outside (see :mod:`cutfem.geometry.cut`).  ngsxfem 2.1 refuses such
a level set: ``CutInfo`` raises "You tried to cut a simplex with a plain geometry lset function"
(after printing the values of the offending sub-simplex; the study captures that output).  So on
the paper's own levels the peer has no answer; the study records the message and runs three
variants:

* ``+eps``: the zero values replaced by +1e-14 (what "zero counts as outside" means in the limit).
  ngsxfem then also activates the tets whose piece cutfem drops because it collapses to a point or
  a segment (a negative node, no positive node, one or two zeros): more active tets and ghost
  faces, a different discrete problem -- the errors differ by 4.9 % at 0.1 and 1.7 % at 0.05;
* ``+eps-cutfem-active``: as above, with those collapsed tets removed from the IF elements (they
  are found around the zero nodes only): cutfem's discrete problem up to O(eps); this is the
  ngsxfem result reported for the paper levels;
* ``shifted``: the torus moved by the tiny offset 1e-6 (sqrt 2, sqrt 3, sqrt 5)/3 in both codes (box
  given explicitly), so that no node is zero and both codes run unchanged.  The shifted problem has
  a different active set from the paper's (13056 against 12452 active tets at 0.1: the collapsed
  tets come back), hence a different error (0.5031 against 0.4819 at 0.1), and the two codes agree
  on it as closely as on the unshifted one.

Timings (seconds; quick and full keep the faster of two runs at spacings >= 0.05, one run below)
-----------------------------------------------------------------------------------------------
ngsxfem: ``mesh`` (materialize cutfem's points/tets, boundary triangles, netgen and NGSolve meshes),
``levelset`` (nodal values, GridFunction), ``cut`` (CutInfo, IF elements, ghost facets, compressed
space), ``assembly`` (bilinear form and the three linear forms), ``solve`` (factorization + three
solves; NGSolve's default ``sparsecholesky``), ``errors``.  NGSolve runs single-threaded (no
``TaskManager``); at spacings >= 0.025 the pipeline is timed once more inside ``TaskManager()``
(all cores, mesh build reused).  cutfem: the problem's own stages ``geometry`` (box, level set,
cut, space), ``assembly``, ``solve`` (:class:`~cutfem.solvers.solve.DirectSolver`: banded Cholesky after
reverse Cuthill-McKee, or SuperLU for wide bands), ``errors``; its total is their sum (the run's wall
time, which also builds pyvista output fields, is recorded as ``wall``).  Same-solver comparison:
the NGSolve matrix exported (CSR) and factorized by cutfem's :class:`~cutfem.solvers.solve.DirectSolver`
(the same factorization choice), ``solve_superlu``.  Ratios are ngsxfem / cutfem.  Where cutfem's
default solver ("auto") is not the direct one (more than ``cutfem.solvers.solve.DIRECT_LIMIT`` unknowns)
cutfem is timed once more with it (``cutfem_auto``).  The structural
difference: ngsxfem's mesh, CutInfo, facet search and element/facet loops visit the whole
background mesh (8 times more per halving of the spacing) while cutfem visits only a band around
the surface (4 times more).

Memory: the NGSolve side needs about 350 bytes per background tet (1.86 GB peak at 4.7M tets,
spacing 0.025); a level whose estimate (:data:`BYTES_PER_TET`) exceeds 90 % of the available
memory is skipped for ngsxfem with the reason recorded (``ngsxfem_skipped``).

The meshed case
---------------
On the flipped and perturbed torus families (seed 0) the cotangent Laplacian with the mixed
Voronoi lumped mass (:func:`cutfem.studies.baselines.cotangent_mean_curvature`) against the stabilized
method (tau_E = 1/10): discrete error ||pi_h H - H_h||_{S_h} (P1 mass matrix), nodal maximum
error, and times (cotangent: the formula on a given mesh, best of three; stabilized: assembly +
solve from the problem's timer; both also end to end including the mesh), with the ratios
cotangent / stabilized.

Fictitious-domain Poisson (``--problem poisson``; ``both`` runs the two comparisons)
-----------------------------------------------------------------------------------
``cutfem.run("poisson-cut")`` (docs/math.md §8: unit ball in its default structured box, gamma = 10
with h_T, gamma_g = 0.1 with h_F^1 on the ghost faces of NEG, u = sin(pi x/2) cos(pi y/3) exp(z/2))
against :func:`ngsxfem_poisson` on the same tets, the same snapped P1 level set (zeros -> +EPS and
the collapsed tets not counted as cut, as above), h_T from netgen's element table, h_F from the
facet normal (:func:`kuhn_face_h`: exact on a Kuhn lattice, where NGSolve offers no longest edge
of a facet), the same quadrature degrees (2 for the form and the volume load, 4 for the Nitsche
load and the errors).  Solvers: each code's fastest for this SPD system -- cutfem's default, CG
with the geometric multigrid on the nested Kuhn lattices; NGSolve's CG with Jacobi ("local"; its
multigrid needs a mesh hierarchy that an imported mesh does not have, BDDC on P1 keeps every
vertex in the coarse space, i.e. a direct solve, CG with h1amg stops at a wrong answer at 40k
unknowns; its sparse Cholesky is timed once per level as ``solve_direct``).  Each level runs both codes ``repeat`` times,
alternating, and reports the median.  Outputs ``peers_poisson.json``/``.csv`` and a table.

Outputs (prefix ``peers``): ``peers.json``, ``peers.csv`` (cut levels), ``peers_meshed.csv``,
``peers.png/.pdf`` (time against active tets for both codes; errors of both codes and their relative
difference; the meshed comparison).  Without ngsolve/xfem, ``run`` writes ``peers.json`` saying so
and returns ``{"skipped": 'install with pip install -e ".[peers]"'}``.
"""

from __future__ import annotations

import gc
import math
import time
from pathlib import Path

import numpy as np

from .common import PAGE_WIDTH, figure_style, pick, save_csv, save_figure, save_json, study_main, torus_family

NAME = "peers"
OUTPUTS = [NAME, f"{NAME}_meshed"]  # peers.json/.csv/.png/.pdf, peers_meshed.csv
POISSON_NAME = f"{NAME}_poisson"  # --problem poisson: peers_poisson.json/.csv
INSTALL = 'install with pip install -e ".[peers]"'
BOX = "-1.6,-1.6,-0.6,1.6,1.6,0.6"
TAU_F = 0.1
TAU_E = 0.1
ORDER = 4
EPS = 1e-14
SHIFT = 1e-6 * np.sqrt([2.0, 3.0, 5.0]) / 3.0
SEED = 0
FAMILIES = ("flipped", "perturbed")
#: the ngsxfem pipeline is timed a second time inside TaskManager() at spacings >= this
TASKMANAGER_DOWN_TO = 0.025
#: ngsxfem is run a second time on tets in cutfem's vertex order at spacings >= this
SAME_ORDER_DOWN_TO = 0.05
#: at spacings >= this, quick and full time both pipelines twice and keep the faster run
REPEAT_DOWN_TO = 0.05


def peer_missing() -> str | None:
    """None when ngsolve and xfem import, else the import error message."""
    try:
        import ngsolve  # noqa: F401
        import xfem  # noqa: F401
    except Exception as exc:  # ImportError, or a broken binary install
        return f"{type(exc).__name__}: {exc}"
    return None


def _say(progress, msg):
    if progress:
        progress(msg)


# ---------------------------------------------------------------------------------------------
# the NGSolve side
# ---------------------------------------------------------------------------------------------


def kuhn_boundary_triangles(box) -> np.ndarray:
    """(k, 3) node ids of the boundary triangles of a StructuredBox, outward oriented (right-hand
    rule), found among the Kuhn tets of the boundary cells only."""
    from cutfem.geometry.numbering import TET_FACES

    tris = []
    nc = box.cells
    for axis in range(3):
        others = [d for d in range(3) if d != axis]
        ga, gb = np.meshgrid(np.arange(nc[others[0]]), np.arange(nc[others[1]]), indexing="ij")
        for side, cell_layer in ((0, 0), (1, nc[axis] - 1)):
            ijk = np.empty(ga.shape + (3,), dtype=np.int64)
            ijk[..., axis], ijk[..., others[0]], ijk[..., others[1]] = cell_layer, ga, gb
            ijk = ijk.reshape(-1, 3)
            cells = ijk[:, 0] + nc[0] * (ijk[:, 1] + nc[1] * ijk[:, 2])
            tets = box.cell_tets(cells)
            level = side * nc[axis]
            for face in TET_FACES:
                f = tets[:, face]
                on = np.all(box.node_index(f)[..., axis] == level, axis=1)
                tris.append(f[on])
    tri = np.concatenate(tris)
    p = box.node_coordinates(tri)
    nrm = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    centre = 0.5 * (box.lower + box.upper)
    inward = np.einsum("ij,ij->i", nrm, centre - p[:, 0]) > 0
    tri[inward, 1], tri[inward, 2] = tri[inward, 2], tri[inward, 1].copy()
    return tri


def ngsolve_mesh(box, orientation="netgen"):
    """The NGSolve mesh of exactly the tets of ``box`` (vertex k = point k, element k = tet k).

    ``orientation``: "netgen" (netgen's convention, negative determinant: vertices 1 and 2 of
    cutfem's positive tets swapped; boundary triangles outward by the right-hand rule) or "cutfem"
    (cutfem's vertex order as is, boundary triangles reversed to match).  Volume integrals and the
    form do not depend on it; the ngsxfem quadrature on S_h does, through the diagonal it picks to
    split quadrilateral pieces (see the module docstring).
    """
    import netgen.meshing as nm
    import ngsolve

    if orientation not in ("netgen", "cutfem"):
        raise ValueError(f"orientation must be 'netgen' or 'cutfem', got {orientation!r}")
    tets = box.tets[:, [0, 2, 1, 3]] if orientation == "netgen" else box.tets
    tri = kuhn_boundary_triangles(box)
    if orientation == "cutfem":
        tri = tri[:, ::-1]
    ngmesh = nm.Mesh(dim=3)
    ngmesh.AddPoints(np.ascontiguousarray(box.points, dtype=float))
    fd = ngmesh.Add(nm.FaceDescriptor(surfnr=1, domin=1, domout=0, bc=1))
    ngmesh.AddElements(dim=3, index=1, data=np.ascontiguousarray(tets, dtype=np.int32), base=0)
    ngmesh.AddElements(dim=2, index=fd, data=np.ascontiguousarray(tri, dtype=np.int32), base=0)
    return ngsolve.Mesh(ngmesh)


def torus_exact_cf(torus):
    """H^e = (k1 + k2)(p(x)) n(p(x)) of cutfem's Torus as an NGSolve CoefficientFunction."""
    from ngsolve import CF, sqrt, x, y, z

    R, r = torus.R, torus.r
    cx, cy, cz = (float(c) for c in torus.center)
    X, Y, Z = x - cx, y - cy, z - cz
    s = sqrt(X * X + Y * Y)
    d = sqrt(Z * Z + (s - R) * (s - R))
    cosp = (s - R) / d
    m = CF(((s - R) / d * X / s, (s - R) / d * Y / s, Z / d))
    return (R + 2 * r * cosp) / (r * (R + r * cosp)) * m


def cutfem_nodal_values(box, levelset) -> np.ndarray:
    """phi at every node of ``box``, with cutfem's snap of near-zero values to exactly zero."""
    from cutfem.geometry.nodal_values import snapped_nodal_values

    return snapped_nodal_values(box, levelset)


def tets_at_nodes(box, node_ids) -> np.ndarray:
    """Ids of the tets of a StructuredBox that contain one of ``node_ids`` (from the <= 8 cells
    around each node, without building the whole mesh)."""
    ijk = box.node_index(np.asarray(node_ids, dtype=np.int64))
    offsets = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)]) - 1
    cells = (ijk[:, None, :] + offsets[None, :, :]).reshape(-1, 3)
    cells = cells[np.all((cells >= 0) & (cells < box.cells), axis=1)]
    cell_ids = np.unique(cells[:, 0] + box.cells[0] * (cells[:, 1] + box.cells[1] * cells[:, 2]))
    tet_ids = (6 * cell_ids[:, None] + np.arange(6)).reshape(-1)
    nodes = box.cell_tets(cell_ids)
    return tet_ids[np.isin(nodes, node_ids).any(axis=1)]


def collapsed_tets(box, values) -> np.ndarray:
    """Tets that ngsxfem (with the zeros of ``values`` made +eps) takes as cut but cutfem does not:
    a negative node, no positive node, and one or two zero nodes (their piece collapses to a point
    or a segment under cutfem's zero rule).  Only tets around zero nodes are visited."""
    zero = np.flatnonzero(values == 0)
    if zero.size == 0:
        return np.zeros(0, dtype=np.int64)
    ids = tets_at_nodes(box, zero)
    v = values[box.cell_tets(ids // 6).reshape(-1, 6, 4)[np.arange(ids.size), ids % 6]]
    nz = np.sum(v == 0, axis=1)
    return ids[np.any(v < 0, axis=1) & ~np.any(v > 0, axis=1) & (nz >= 1) & (nz <= 2)]


class _CapturedStdout:
    """Capture what C++ code writes to file descriptor 1 (ngsxfem prints before it raises)."""

    def __enter__(self):
        import ctypes
        import os
        import sys
        import tempfile

        sys.stdout.flush()
        self._libc = ctypes.CDLL(None)
        self._libc.fflush(None)
        self._file = tempfile.TemporaryFile()
        self._saved = os.dup(1)
        os.dup2(self._file.fileno(), 1)
        self.text = ""
        return self

    def __exit__(self, *exc):
        import os

        self._libc.fflush(None)
        os.dup2(self._saved, 1)
        os.close(self._saved)
        self._file.seek(0)
        self.text = self._file.read().decode(errors="replace")
        self._file.close()
        return False


def _superlu_same_as_cutfem(mat):
    """Factorize an NGSolve sparse matrix with cutfem's DirectSolver; (solver, CSR matrix)."""
    import scipy.sparse as sp

    from cutfem.solvers.direct import DirectSolver

    vals, cols, rows = mat.CSR()
    A = sp.csr_matrix((np.array(vals), np.array(cols), np.array(rows)), shape=(mat.height, mat.width))
    if sp.triu(A, 1).nnz == 0:  # symmetric storage: lower triangle only
        A = (A + A.T - sp.diags(A.diagonal())).tocsr()
    return DirectSolver(A), A


#: bytes per background tet that the NGSolve side needs (measured: 1.86 GB peak for the whole pipeline at 4.7M tets,
#: spacing 0.025, including cutfem's materialized points/tets), with a margin
BYTES_PER_TET = 400


def available_memory() -> float | None:
    """MemAvailable in bytes (Linux), else None."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return float(line.split()[1]) * 1024
    except OSError:
        return None
    return None


class NgBackground:
    """cutfem's structured background box and the NGSolve mesh of the same tets, with the time
    spent building both (materializing points/tets included)."""

    def __init__(self, spacing, levelset, box=None, orientation="netgen"):
        from cutfem.problems.common import background_for

        t0 = time.perf_counter()
        self.box = background_for(levelset, spacing, "structured", box)  # a fresh box: nothing cached
        self.mesh = ngsolve_mesh(self.box, orientation)
        self.orientation = orientation
        self.seconds = time.perf_counter() - t0
        self.box.__dict__.pop("tets", None)  # free the materialized tets (NGSolve has its own copy)
        gc.collect()


def ngsxfem_mean_curvature(spacing, levelset, box=None, zero_rule="none", tau_f=TAU_F, order=ORDER,
                           inverse="sparsecholesky", superlu=True, background=None, orientation="netgen") -> dict:
    """Solve the cut mean curvature problem with ngsxfem on cutfem's structured background mesh.

    ``zero_rule``: "none" (the snapped values as they are: ngsxfem 2.1 raises on exact zeros),
    "+eps" (zeros -> +EPS), "+eps-cutfem-active" (and the IF elements restricted to cutfem's
    active tets).  ``background``: a :class:`NgBackground` to reuse (its build time is reported as
    the mesh time), else one is built with ``orientation``.  ``superlu``: also solve with cutfem's
    DirectSolver on the exported matrix.  Returns a record with the error, sizes and stage times.
    """
    import ngsolve as ngs
    from ngsolve import H1, GridFunction, Id, InnerProduct, Integrate, LinearForm, OuterProduct, grad, specialcf, sqrt
    from xfem import IF, CutInfo, GetDofsOfElements, GetFacetsWithNeighborTypes, RestrictedBilinearForm, dCut

    T = {}
    reused = background is not None
    if background is None:
        background = NgBackground(spacing, levelset, box, orientation)
    bg, mesh = background.box, background.mesh
    T["mesh"] = background.seconds

    t0 = time.perf_counter()
    values = cutfem_nodal_values(bg, levelset)
    zero_nodes = int(np.sum(values == 0))
    snapped = values
    if zero_rule != "none":
        values = values.copy()
        values[values == 0] = EPS
    V = H1(mesh, order=1)
    lset = GridFunction(V)
    lset.vec.FV().NumPy()[:] = values
    T["levelset"] = time.perf_counter() - t0

    rec = {"zero_rule": zero_rule, "zero_nodes": zero_nodes, "background_nodes": int(mesh.nv),
           "background_tets": int(mesh.ne), "mesh_reused": reused, "orientation": background.orientation}
    t0 = time.perf_counter()
    try:
        with _CapturedStdout() as cap:
            ci = CutInfo(mesh, lset)
    except Exception as exc:  # ngsxfem refuses level sets with exact zeros on sub-simplices
        T["cut"] = time.perf_counter() - t0
        rec.update(failed=f"{type(exc).__name__}: {str(exc).strip()}", printed=cap.text.split(), time=T)
        return rec
    els = ci.GetElementsOfType(IF)
    if zero_rule == "+eps-cutfem-active":
        els = ngs.BitArray(els)
        drop = collapsed_tets(bg, snapped)
        for k in drop.tolist():
            els.Clear(k)
        rec["dropped_collapsed_tets"] = int(drop.size)
    facets = GetFacetsWithNeighborTypes(mesh, a=els, b=els, bnd_val_a=False, bnd_val_b=False, use_and=True)
    Vf = H1(mesh, order=1, dgjumps=True)
    Vc = ngs.Compress(Vf, GetDofsOfElements(Vf, els))
    T["cut"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    u, v = Vc.TnT()
    g = grad(lset)
    n = g / sqrt(InnerProduct(g, g))
    P = Id(3) - OuterProduct(n, n)
    ds = dCut(levelset=lset, domain_type=IF, definedonelements=els, order=2)
    dw = ngs.dx(skeleton=True, definedonelements=facets)
    nF = specialcf.normal(3)
    a = RestrictedBilinearForm(Vc, element_restriction=els, facet_restriction=facets, symmetric=True, check_unused=False)
    a += u * v * ds
    a += tau_f * InnerProduct(grad(u) - grad(u.Other()), nF) * InnerProduct(grad(v) - grad(v.Other()), nF) * dw
    a.Assemble()
    rhs = []
    for k in range(3):
        f = LinearForm(Vc)
        f += (P * grad(v))[k] * ds
        f.Assemble()
        rhs.append(f)
    T["assembly"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    inv = a.mat.Inverse(Vc.FreeDofs(), inverse=inverse)
    H = []
    for k in range(3):
        gf = GridFunction(Vc)
        gf.vec.data = inv * rhs[k].vec
        H.append(gf)
    T["solve"] = time.perf_counter() - t0
    del inv

    t0 = time.perf_counter()
    Hh = ngs.CF(tuple(H))
    diff = Hh - torus_exact_cf(levelset)
    err = math.sqrt(Integrate(InnerProduct(diff, diff) * dCut(levelset=lset, domain_type=IF, definedonelements=els, order=order), mesh))
    T["errors"] = time.perf_counter() - t0
    area = Integrate(ngs.CF(1.0) * dCut(levelset=lset, domain_type=IF, definedonelements=els, order=1), mesh)

    rec.update(
        l2_error=err,
        area=area,
        dofs=int(Vc.ndof),
        active_tets=int(els.NumSet()),
        interior_faces=int(facets.NumSet()),
        solver=inverse,
        time=T,
        total=sum(T.values()),
    )
    if superlu:
        B = np.stack([f.vec.FV().NumPy() for f in rhs], axis=1)
        t0 = time.perf_counter()
        solver, _ = _superlu_same_as_cutfem(a.mat)
        X = solver.solve(B)
        rec["solve_superlu"] = time.perf_counter() - t0
        Xn = np.stack([gf.vec.FV().NumPy() for gf in H], axis=1)
        rec["superlu_vs_native"] = float(np.abs(X - Xn).max() / np.abs(Xn).max())
    return rec


# ---------------------------------------------------------------------------------------------
# the cutfem side
# ---------------------------------------------------------------------------------------------


def cutfem_mean_curvature(spacing, levelset="torus", box=None, tau_f=TAU_F, solver="direct") -> dict:
    import cutfem

    kw = {} if box is None else {"box": box}
    t0 = time.perf_counter()
    res = cutfem.run("mean-curvature-cut", levels=[spacing], surface=levelset, tau_f=tau_f, solver=solver, **kw)
    wall = time.perf_counter() - t0
    r = res.records[0]
    rec = {k: r[k] for k in ("l2_error", "area", "dofs", "active_tets", "interior_faces", "background_nodes", "solver") if k in r}
    rec["time"] = dict(r["time"])
    rec["total"] = sum(r["time"].values())
    rec["wall"] = wall
    return rec


def _direct_limit():
    try:
        from cutfem.solvers.solve import DIRECT_LIMIT

        return DIRECT_LIMIT
    except ImportError:
        return 20_000


def _rel(a, b):
    return abs(a - b) / abs(b)


def _sig_digits(rel):
    return float("inf") if rel == 0 else float(-math.log10(rel))


def _stage_ratios(ng, cf):
    cg, ngt = cf["time"], ng["time"]
    ratios = {
        "geometry": (ngt["mesh"] + ngt["levelset"] + ngt["cut"]) / cg["geometry"],
        "assembly": ngt["assembly"] / cg["assembly"],
        "solve": ngt["solve"] / cg["solve"],
        "errors": ngt["errors"] / cg["errors"],
    }
    if "solve_superlu" in ng:
        ratios["solve_same_superlu"] = ng["solve_superlu"] / cg["solve"]
    return ratios


def compare_level(spacing, variant="paper", progress=None, taskmanager=False, repeat=1) -> dict:
    """Both codes at one spacing.  ``variant``: "paper" (the torus at the origin; when nodal values
    are zero, ngsxfem with the zero rules of the module docstring, the reported one being
    "+eps-cutfem-active") or "shifted" (torus moved by SHIFT, box given).  ``taskmanager``: time the
    ngsxfem pipeline once more inside ``ngsolve.TaskManager()`` (all cores; mesh build reused).
    ``repeat``: run both codes' pipelines this many times and keep the fastest run of each (the
    machine may be shared)."""
    import os

    import ngsolve

    from cutfem.geometry.shapes import Torus
    from cutfem.problems.common import background_for

    if variant == "shifted":
        torus, box = Torus(center=tuple(SHIFT)), BOX
    else:
        torus, box = Torus(), None
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    _say(progress, f"cut {variant} spacing {spacing}: cutfem")
    cf = min((cutfem_mean_curvature(spacing, torus, box) for _ in range(repeat)), key=lambda r: r["total"])
    gc.collect()
    out = {"spacing": spacing, "variant": variant, "cutfem": cf, "load_average": load, "repeat": repeat}
    if cf["dofs"] > _direct_limit():  # cutfem's default solver is not the direct one here: time it too
        _say(progress, f"cut {variant} spacing {spacing}: cutfem, solver auto")
        r = cutfem_mean_curvature(spacing, torus, box, solver="auto")
        out["cutfem_auto"] = dict(r, rel_diff_to_direct=_rel(r["l2_error"], cf["l2_error"]))
        gc.collect()
    n_tets = background_for(torus, spacing, "structured", box).n_tets  # lazy: nothing is built
    need, avail = BYTES_PER_TET * n_tets, available_memory()
    if avail is not None and need > 0.9 * avail:
        out["ngsxfem_skipped"] = f"the NGSolve mesh of {n_tets} tets needs about {need / 1e9:.1f} GB, {avail / 1e9:.1f} GB available"
        _say(progress, f"  ngsxfem skipped: {out['ngsxfem_skipped']}")
        return out
    _say(progress, f"cut {variant} spacing {spacing}: ngsxfem")
    background = NgBackground(spacing, torus, box)
    ng = ngsxfem_mean_curvature(spacing, torus, box, background=background)
    out["ngsxfem"] = ng
    if "failed" in ng:
        _say(progress, f"  ngsxfem failed ({ng['failed']}); zero rules +eps")
        out["ngsxfem_failed"] = ng["failed"]
        out["variants"] = {}
        for rule in ("+eps", "+eps-cutfem-active"):
            gc.collect()
            r = ngsxfem_mean_curvature(spacing, torus, box, zero_rule=rule, superlu=rule != "+eps", background=background)
            out["variants"][rule] = dict(r, rel_diff=_rel(r["l2_error"], cf["l2_error"]))
        out["ngsxfem"] = ng = out["variants"]["+eps-cutfem-active"]
    if taskmanager:
        gc.collect()
        with ngsolve.TaskManager():
            r = ngsxfem_mean_curvature(spacing, torus, box, zero_rule=ng["zero_rule"], superlu=False, background=background)
        out["ngsxfem_taskmanager"] = {"time": r["time"], "total": r["total"], "l2_error": r["l2_error"], "cores": os.cpu_count()}
    del background
    gc.collect()
    for _ in range(repeat - 1):
        r = ngsxfem_mean_curvature(spacing, torus, box, zero_rule=ng["zero_rule"])
        if r["total"] < ng["total"]:
            ng = dict(ng, time=r["time"], total=r["total"], solve_superlu=min(r["solve_superlu"], ng["solve_superlu"]))
        gc.collect()
    out["ngsxfem"] = ng
    if spacing >= SAME_ORDER_DOWN_TO:
        r = ngsxfem_mean_curvature(spacing, torus, box, zero_rule=ng["zero_rule"], superlu=False, orientation="cutfem")
        out["same_vertex_order"] = {"l2_error": r["l2_error"], "rel_diff": _rel(r["l2_error"], cf["l2_error"]), "total": r["total"]}
        gc.collect()
    out["rel_diff"] = _rel(ng["l2_error"], cf["l2_error"])
    out["significant_digits"] = _sig_digits(out["rel_diff"])
    out["same_problem"] = all(ng[k] == cf[k] for k in ("dofs", "active_tets", "interior_faces"))
    out["time_ratio"] = ng["total"] / cf["total"]
    out["stage_ratio"] = _stage_ratios(ng, cf)
    _say(progress, f"  errors {ng['l2_error']:.8g} (ngsxfem) {cf['l2_error']:.8g} (cutfem), rel diff {out['rel_diff']:.2e}, "
                   f"time {ng['total']:.2f} s / {cf['total']:.2f} s")
    return out


# ---------------------------------------------------------------------------------------------
# fictitious-domain Poisson (docs/math.md §8) in both codes
# ---------------------------------------------------------------------------------------------

#: the Poisson comparison: unit ball in cutfem's default structured box, its default penalties
POISSON_GAMMA = 10.0
POISSON_GAMMA_G = 0.1


def poisson_exact_cf():
    """(u, grad u, f) of cutfem's manufactured Poisson solution as NGSolve CoefficientFunctions:
    u = sin(pi x/2) cos(pi y/3) exp(z/2), f = -Lap u = (pi^2/4 + pi^2/9 - 1/4) u."""
    from ngsolve import CF, cos, exp, sin, x, y, z

    a, b, c = math.pi / 2, math.pi / 3, 0.5
    u = sin(a * x) * cos(b * y) * exp(c * z)
    grad = CF((a * cos(a * x) * cos(b * y) * exp(c * z), -b * sin(a * x) * sin(b * y) * exp(c * z), c * u))
    return u, grad, (a * a + b * b - c * c) * u


def kuhn_face_h(spacing):
    """h_F = the longest edge of a facet of a Kuhn lattice of the given spacing, as an NGSolve
    CoefficientFunction on the skeleton (NGSolve has no longest-edge-of-the-facet function and no
    vectorized facet-to-vertex table to build one from).  A facet of a Kuhn tet either lies in a
    face of its cube (half a square: longest edge sqrt(2) s, normal along an axis, sum n_i^4 = 1) or
    contains the cube's diagonal (edges s, sqrt(2) s, sqrt(3) s, normal (0, 1, -1)/sqrt(2) up to
    permutation and sign, sum n_i^4 = 1/2); the normal tells them apart."""
    from ngsolve import IfPos, specialcf

    n = specialcf.normal(3)
    n4 = n[0] ** 4 + n[1] ** 4 + n[2] ** 4
    return IfPos(n4 - 0.75, math.sqrt(2.0) * spacing, math.sqrt(3.0) * spacing)


def element_longest_edges(mesh) -> np.ndarray:
    """(ne,) longest edge h_T of each tet of an NGSolve mesh (vectorized over netgen's element table)."""
    tets = mesh.ngmesh.Elements3D().NumPy()["nodes"].astype(np.int64) - 1  # netgen's nodes are 1-based
    p = np.asarray(mesh.ngmesh.Coordinates())
    h = np.zeros(len(tets))
    for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)):
        h = np.maximum(h, np.linalg.norm(p[tets[:, i]] - p[tets[:, j]], axis=1))
    return h


def ngsxfem_poisson(spacing, levelset=None, gamma=POISSON_GAMMA, gamma_g=POISSON_GAMMA_G, inverse="cg-local",
                    background=None, also_direct=False) -> dict:
    """Fictitious-domain Poisson (docs/math.md §8) with ngsxfem on cutfem's structured background.

    The same problem as ``cutfem.run("poisson-cut")``: P1 on the tets that meet Omega_h
    (``HASNEG``; the H1 space with ``dgjumps=True`` compressed to their dofs), the form
    (grad u, grad v)_{Omega_h} - (n.grad u, v)_Gamma - (u, n.grad v)_Gamma + (gamma/h_T)(u, v)_Gamma
    + gamma_g sum_F h_F ([n_F.grad u], [n_F.grad v])_F, n = grad phi_h/|grad phi_h|, h_T the longest
    edge of the cut tet (an order-0 L2 GridFunction from netgen's element table), h_F the longest
    edge of the facet (:func:`kuhn_face_h`), the ghost facets the interior facets between two
    HASNEG tets of which one is cut (``GetFacetsWithNeighborTypes(a=HASNEG, b=cut)``).  Quadrature:
    order 2 for the form and the volume load (cutfem: degree 2), order 4 for the Nitsche load and
    the errors (cutfem: degree 4).  Zero nodal values (nodes on the sphere) are made +EPS, and the
    tets whose piece of Gamma_h collapses under cutfem's zero rule (:func:`collapsed_tets`) are not
    counted as cut for the ghost facets (their Gamma pieces have area O(EPS)).  ``inverse``: an
    NGSolve direct inverse ("sparsecholesky", ...) or "cg-" + an NGSolve preconditioner name: CG to
    a relative residual of 1e-10 (default "cg-local", Jacobi: the fastest here; "cg-h1amg" stops at a
    wrong answer at 40k unknowns, L2 error 1.1e-2 against 9.8e-4, "cg-bddc" on P1 is a direct solve and slower).  ``also_direct``: time NGSolve's
    sparse Cholesky on the same system too (``solve_direct``, not in the total).  Returns errors,
    sizes and stage times.
    """
    import ngsolve as ngs
    from ngsolve import H1, L2, GridFunction, InnerProduct, Integrate, LinearForm, grad, specialcf, sqrt
    from xfem import HASNEG, IF, NEG, CutInfo, GetDofsOfElements, GetFacetsWithNeighborTypes, RestrictedBilinearForm, dCut

    from cutfem.geometry.shapes import Sphere

    levelset = Sphere() if levelset is None else levelset
    T = {}
    if background is None:
        background = NgBackground(spacing, levelset)
    bg, mesh = background.box, background.mesh
    T["mesh"] = background.seconds

    t0 = time.perf_counter()
    snapped = cutfem_nodal_values(bg, levelset)
    values = snapped.copy()
    values[values == 0] = EPS
    lset = GridFunction(H1(mesh, order=1))
    lset.vec.FV().NumPy()[:] = values
    T["levelset"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    ci = CutInfo(mesh, lset)
    hasneg = ci.GetElementsOfType(HASNEG)
    cut = ngs.BitArray(ci.GetElementsOfType(IF))
    drop = collapsed_tets(bg, snapped)
    for k in drop.tolist():  # only around the nodes on the sphere
        cut.Clear(k)
    ghost = GetFacetsWithNeighborTypes(mesh, a=hasneg, b=cut, bnd_val_a=False, bnd_val_b=False, use_and=True)
    Vf = H1(mesh, order=1, dgjumps=True)
    V = ngs.Compress(Vf, GetDofsOfElements(Vf, hasneg))
    hT = GridFunction(L2(mesh, order=0))
    hT.vec.FV().NumPy()[:] = element_longest_edges(mesh)
    T["cut"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    u_ex, grad_ex, f = poisson_exact_cf()
    u, v = V.TnT()
    g = grad(lset)
    n = g / sqrt(InnerProduct(g, g))
    dxn = dCut(levelset=lset, domain_type=NEG, definedonelements=hasneg, order=2)
    ds = dCut(levelset=lset, domain_type=IF, definedonelements=cut, order=2)
    ds4 = dCut(levelset=lset, domain_type=IF, definedonelements=cut, order=4)
    dw = ngs.dx(skeleton=True, definedonelements=ghost)
    nF = specialcf.normal(3)
    a = RestrictedBilinearForm(V, element_restriction=hasneg, facet_restriction=ghost, symmetric=True, check_unused=False)
    a += InnerProduct(grad(u), grad(v)) * dxn
    a += (-InnerProduct(grad(u), n) * v - InnerProduct(grad(v), n) * u + gamma / hT * u * v) * ds
    a += gamma_g * kuhn_face_h(spacing) * InnerProduct(grad(u) - grad(u.Other()), nF) * InnerProduct(grad(v) - grad(v.Other()), nF) * dw
    pre = ngs.Preconditioner(a, inverse[3:]) if inverse.startswith("cg-") else None
    a.Assemble()
    b = LinearForm(V)
    b += f * v * dxn
    b += u_ex * (-InnerProduct(grad(v), n) + gamma / hT * v) * ds4
    b.Assemble()
    T["assembly"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if pre is None:
        inv = a.mat.Inverse(V.FreeDofs(), inverse=inverse)
    else:
        inv = ngs.solvers.CGSolver(a.mat, pre.mat, tol=1e-10, maxiter=5000)
    uh = GridFunction(V)
    uh.vec.data = inv * b.vec
    T["solve"] = time.perf_counter() - t0
    iterations = getattr(inv, "iterations", 0)
    del inv
    extra = {}
    if also_direct:
        t0 = time.perf_counter()
        ud = GridFunction(V)
        ud.vec.data = a.mat.Inverse(V.FreeDofs(), inverse="sparsecholesky") * b.vec
        extra["solve_direct"] = time.perf_counter() - t0
        x, xd = uh.vec.FV().NumPy(), ud.vec.FV().NumPy()
        extra["direct_vs_solver"] = float(np.abs(x - xd).max() / np.abs(xd).max())
        del ud

    t0 = time.perf_counter()
    dxe = dCut(levelset=lset, domain_type=NEG, definedonelements=hasneg, order=4)
    e = uh - u_ex
    eg = grad(uh) - grad_ex
    l2 = math.sqrt(Integrate(e * e * dxe, mesh))
    h1 = math.sqrt(Integrate(InnerProduct(eg, eg) * dxe, mesh))
    T["errors"] = time.perf_counter() - t0
    volume = Integrate(ngs.CF(1.0) * dxn, mesh)
    return {
        "l2_error": l2,
        "h1_error": h1,
        "volume": volume,
        "dofs": int(V.ndof),
        "active_tets": int(hasneg.NumSet()),
        "cut_tets": int(cut.NumSet()),
        "ghost_faces": int(ghost.NumSet()),
        "zero_nodes": int(np.sum(snapped == 0)),
        "dropped_collapsed_tets": int(drop.size),
        "background_nodes": int(mesh.nv),
        "background_tets": int(mesh.ne),
        "solver": inverse,
        "solver_iterations": int(iterations),
        "time": T,
        "total": sum(T.values()),
        **extra,
    }

def cutfem_poisson(spacing, solver="auto") -> dict:
    """cutfem's ``poisson-cut`` at one spacing (unit sphere, its default box, gamma = 10, gamma_g = 0.1);
    stage times from the problem's timer, total = their sum, wall = the whole run."""
    import cutfem

    t0 = time.perf_counter()
    res = cutfem.run("poisson-cut", levels=[spacing], gamma=POISSON_GAMMA, gamma_g=POISSON_GAMMA_G, solver=solver)
    wall = time.perf_counter() - t0
    r = res.records[0]
    rec = {k: r[k] for k in ("l2_error", "h1_error", "volume", "dofs", "background_nodes", "solver", "solver_iterations")}
    rec["cut_tets"] = r["pieces"]  # the tets the surface cuts (active_tets: those of the NEG field)
    rec["time"] = dict(r["time"])
    rec["total"] = sum(r["time"].values())
    rec["wall"] = wall
    return rec


def cutfem_poisson_sets(spacing, levelset=None) -> dict:
    """The sizes of cutfem's Poisson problem that ngsxfem reports too: the tets of NEG (the active
    set) and its ghost faces (untimed: one cut of the background)."""
    from cutfem.geometry.cut import cut_mesh
    from cutfem.geometry.shapes import Sphere
    from cutfem.geometry.markers import NEG
    from cutfem.problems.common import background_for

    levelset = Sphere() if levelset is None else levelset
    cut = cut_mesh(background_for(levelset, spacing), levelset)
    return {"active_tets": int(cut.elements(NEG).n_elements), "ghost_faces": int(cut.ghost_facets(NEG).n_facets)}


def _median_run(runs):
    """The run with the median total (the lower middle one for an even count), with every total kept."""
    ordered = sorted(runs, key=lambda r: r["total"])
    return dict(ordered[(len(ordered) - 1) // 2], totals=[r["total"] for r in runs])


def compare_poisson_level(spacing, progress=None, repeat=1, also_direct=False) -> dict:
    """Both codes on the fictitious-domain Poisson problem at one spacing, ``repeat`` times each,
    alternating (cutfem, ngsxfem, cutfem, ...); the run with the median total is reported.
    ``also_direct``: the first ngsxfem run also times NGSolve's sparse Cholesky (``solve_direct``)."""
    import os

    from cutfem.geometry.shapes import Sphere

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    cfs, ngs_ = [], []
    for i in range(repeat):
        _say(progress, f"poisson spacing {spacing}: cutfem ({i + 1}/{repeat})")
        cfs.append(cutfem_poisson(spacing))
        gc.collect()
        _say(progress, f"poisson spacing {spacing}: ngsxfem ({i + 1}/{repeat})")
        ngs_.append(ngsxfem_poisson(spacing, Sphere(), also_direct=also_direct and i == 0))
        gc.collect()
    cf, ng = _median_run(cfs), _median_run(ngs_)
    if also_direct:
        ng.update({k: ngs_[0][k] for k in ("solve_direct", "direct_vs_solver")})
    cf.update(cutfem_poisson_sets(spacing))
    out = {"spacing": spacing, "cutfem": cf, "ngsxfem": ng, "load_average": load, "repeat": repeat,
           "same_problem": all(ng[k] == cf[k] for k in ("dofs", "active_tets", "cut_tets", "ghost_faces")),
           "rel_diff_l2": _rel(ng["l2_error"], cf["l2_error"]), "rel_diff_h1": _rel(ng["h1_error"], cf["h1_error"]),
           "rel_diff_volume": _rel(ng["volume"], cf["volume"]), "time_ratio": ng["total"] / cf["total"]}
    _say(progress, f"  L2 {ng['l2_error']:.8g} (ngsxfem) {cf['l2_error']:.8g} (cutfem), rel diff {out['rel_diff_l2']:.1e}; "
                   f"time {ng['total']:.2f} s / {cf['total']:.2f} s")
    return out


def _poisson_row(c):
    cf, ng = c["cutfem"], c["ngsxfem"]
    row = {"spacing": c["spacing"], "dofs": cf["dofs"], "active_tets": cf["active_tets"], "ghost_faces": cf["ghost_faces"],
           "same_problem": c["same_problem"], "l2_cutfem": cf["l2_error"], "l2_ngsxfem": ng["l2_error"], "rel_diff_l2": c["rel_diff_l2"],
           "h1_cutfem": cf["h1_error"], "h1_ngsxfem": ng["h1_error"], "rel_diff_h1": c["rel_diff_h1"],
           "time_cutfem": cf["total"], "time_ngsxfem": ng["total"], "time_ratio": c["time_ratio"],
           "cutfem_solver": cf["solver"], "cutfem_iterations": cf["solver_iterations"], "ngsxfem_solver": ng["solver"],
           "ngsxfem_iterations": ng["solver_iterations"], "ngsxfem_solve_direct": ng.get("solve_direct"), "runs": c["repeat"]}
    row.update({f"cutfem_{k}": v for k, v in cf["time"].items()})
    row.update({f"ngsxfem_{k}": v for k, v in ng["time"].items()})
    return row


def run_poisson(out: Path, size: str = "quick", progress=None) -> dict:
    """The Poisson comparison: ``peers_poisson.json`` / ``.csv`` and a table on standard output."""
    out = Path(out)
    missing = peer_missing()
    if missing is not None:
        print(f"peers: ngsolve/xfem not importable ({missing}); {INSTALL}")
        save_json(out, POISSON_NAME, {"size": size, "peer": "ngsxfem", "available": False, "reason": missing, "skipped": INSTALL})
        return {"skipped": INSTALL}
    import ngsolve

    spacings = pick(size, [0.2], [0.1, 0.05], [0.05, 0.035, 0.025])
    levels = [compare_poisson_level(s, progress, repeat=1 if size == "tiny" or s < 0.05 else 3, also_direct=s >= 0.035)
              for s in spacings]
    rows = [_poisson_row(c) for c in levels]
    save_json(out, POISSON_NAME, {
        "size": size, "peer": "ngsxfem", "available": True,
        "versions": {"ngsolve": ngsolve.__version__, "xfem": _xfem_version()},
        "problem": {"domain": "unit ball (cutfem's default structured box)", "gamma": POISSON_GAMMA, "gamma_g": POISSON_GAMMA_G,
                    "nitsche_h": "h_T, longest edge of the cut tet", "ghost_h": "h_F^1, longest edge of the facet",
                    "exact": "sin(pi x/2) cos(pi y/3) exp(z/2)", "zero_nodal_values": f"ngsxfem: +{EPS:g}, collapsed tets not cut"},
        "solvers": {"cutfem": "solve(method='auto'): CG + geometric multigrid on the nested Kuhn lattices (direct up to 5000 unknowns)",
                    "ngsxfem": "NGSolve CG (rel. residual 1e-10) with Jacobi ('local'); solve_direct: its sparsecholesky"},
        "threads": "NGSolve without TaskManager (one thread); cutfem numpy/scipy",
        "timing": "median total of 3 alternating runs per code at spacings >= 0.05, one run below",
        "levels": levels, "table": rows,
    })
    save_csv(out, POISSON_NAME, rows)
    print(poisson_table(rows))
    return {"size": size, "table": rows}


def poisson_table(rows) -> str:
    """The Poisson comparison as a fixed-width text table."""
    head = f"{'spacing':>8} {'unknowns':>9} {'L2 cutfem':>11} {'L2 ngsxfem':>11} {'rel':>8} {'H1 cutfem':>10} {'H1 ngsxfem':>10} " \
           f"{'t cutfem':>9} {'t ngsxfem':>9} {'ratio':>6}"
    lines = [head]
    for r in rows:
        lines.append(f"{r['spacing']:>8g} {r['dofs']:>9d} {r['l2_cutfem']:>11.5e} {r['l2_ngsxfem']:>11.5e} {r['rel_diff_l2']:>8.1e} "
                     f"{r['h1_cutfem']:>10.5e} {r['h1_ngsxfem']:>10.5e} {r['time_cutfem']:>8.2f}s {r['time_ngsxfem']:>8.2f}s {r['time_ratio']:>6.1f}")
    return "\n".join(lines)

# ---------------------------------------------------------------------------------------------
# the meshed case: cotangent Laplacian with lumped mass against the stabilized method
# ---------------------------------------------------------------------------------------------


def meshed_level(family, n) -> list[dict]:
    """Two rows (cotangent + Voronoi lumped mass, stabilized tau_E = 1/10) on one torus mesh."""
    import cutfem
    from cutfem.studies.baselines import cotangent_mean_curvature
    from cutfem.geometry.shapes import Torus
    from cutfem.fem.spaces import SurfaceP1Space
    from cutfem.geometry.surface_meshes import torus_mesh

    t0 = time.perf_counter()
    mesh = torus_mesh(n, family=family, seed=SEED)
    t_mesh = time.perf_counter() - t0
    space = SurfaceP1Space(mesh)
    He = Torus().exact_mean_curvature_vector(mesh.points)
    rows = []
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        H = cotangent_mean_curvature(mesh.points, mesh.triangles, mass="voronoi")
        best = min(best, time.perf_counter() - t0)
    rows.append(_meshed_row(family, n, mesh, "cotan-voronoi", H, He, space, best, best + t_mesh))
    t0 = time.perf_counter()
    res = cutfem.run("mean-curvature-meshed", levels=[n], surface="torus", tau_e=TAU_E, **torus_family(family, SEED))
    wall = time.perf_counter() - t0
    rec = res.records[0]
    H = np.asarray(rec["fields"]["surface"].point_data["H_h"])
    secs = rec["time"].get("assembly", 0.0) + rec["time"].get("solve", 0.0)
    rows.append(_meshed_row(family, n, mesh, "stabilized", H, He, space, secs, sum(rec["time"].values()), wall=wall))
    rows[1]["error_ratio_cotan_over_stabilized"] = rows[0]["discrete_error"] / rows[1]["discrete_error"]
    rows[1]["time_ratio_cotan_over_stabilized"] = rows[0]["seconds"] / rows[1]["seconds"]
    return rows


def _meshed_row(family, n, mesh, method, H, He, space, secs, end_to_end, wall=None):
    from cutfem.fem.norms import discrete_error

    e = H - He
    row = {
        "family": family,
        "n": n,
        "nodes": int(mesh.n_points),
        "h": float(mesh.n_points) ** -0.5,
        "method": method,
        "discrete_error": discrete_error(space, e),
        "max_error": float(np.linalg.norm(e, axis=1).max()),
        "seconds": secs,
        "end_to_end": end_to_end,
    }
    if wall is not None:
        row["wall"] = wall
    return row


# ---------------------------------------------------------------------------------------------
# the study
# ---------------------------------------------------------------------------------------------


def _cut_row(c):
    cf, ng = c["cutfem"], c.get("ngsxfem")
    row = {
        "variant": c["variant"],
        "spacing": c["spacing"],
        "active_tets": cf["active_tets"],
        "dofs": cf["dofs"],
        "same_problem": c.get("same_problem"),
        "zero_nodes": None if ng is None else ng.get("zero_nodes", 0),
        "ngsxfem_zero_rule": None if ng is None else ng.get("zero_rule"),
        "error_cutfem": cf["l2_error"],
        "error_ngsxfem": None if ng is None else ng["l2_error"],
        "rel_diff": c.get("rel_diff"),
        "time_cutfem": cf["total"],
        "time_ngsxfem": None if ng is None else ng["total"],
        "time_ratio": c.get("time_ratio"),
    }
    for k, v in cf["time"].items():
        row[f"cutfem_{k}"] = v
    if ng is not None:
        for k, v in ng["time"].items():
            row[f"ngsxfem_{k}"] = v
        if "solve_superlu" in ng:
            row["ngsxfem_solve_superlu"] = ng["solve_superlu"]
        for k, v in c["stage_ratio"].items():
            row[f"ratio_{k}"] = v
    if "ngsxfem_taskmanager" in c:
        row["time_ngsxfem_taskmanager"] = c["ngsxfem_taskmanager"]["total"]
        row["time_ratio_taskmanager"] = c["ngsxfem_taskmanager"]["total"] / cf["total"]
    if "cutfem_auto" in c:
        row["cutfem_auto_solver"] = c["cutfem_auto"]["solver"]
        row["time_cutfem_auto"] = c["cutfem_auto"]["total"]
        row["cutfem_auto_solve"] = c["cutfem_auto"]["time"]["solve"]
        if row["time_ngsxfem"] is not None:
            row["time_ratio_vs_cutfem_auto"] = row["time_ngsxfem"] / c["cutfem_auto"]["total"]
    if "same_vertex_order" in c:
        row["error_ngsxfem_cutfem_order"] = c["same_vertex_order"]["l2_error"]
        row["rel_diff_cutfem_order"] = c["same_vertex_order"]["rel_diff"]
    if "ngsxfem_skipped" in c:
        row["ngsxfem_skipped"] = c["ngsxfem_skipped"]
    for rule, r in c.get("variants", {}).items():
        row[f"error_ngsxfem{rule}"] = r["l2_error"]
        row[f"rel_diff{rule}"] = r["rel_diff"]
    return row


def run(out: Path, size: str = "quick", progress=None) -> dict:
    out = Path(out)
    missing = peer_missing()
    if missing is not None:
        msg = f"peers: ngsolve/xfem not importable ({missing}); {INSTALL}"
        print(msg)
        save_json(out, NAME, {"size": size, "peer": "ngsxfem", "available": False, "reason": missing, "skipped": INSTALL})
        return {"skipped": INSTALL}

    import ngsolve

    spacings = pick(size, [0.2], [0.2, 0.1, 0.05], [0.2, 0.1, 0.05, 0.025, 0.0125])
    shifted = pick(size, [], [0.1, 0.05], [0.1, 0.05, 0.025, 0.0125])
    levels_n = pick(size, [16, 32], [16, 32, 64, 128], [16, 32, 64, 128, 256, 512])

    repeat = pick(size, 1, 2, 2)
    cut = [compare_level(s, variant, progress, taskmanager=s >= TASKMANAGER_DOWN_TO, repeat=repeat if s >= REPEAT_DOWN_TO else 1)
           for variant, levels in (("paper", spacings), ("shifted", shifted)) for s in levels]
    meshed = []
    for family in FAMILIES:
        for n in levels_n:
            _say(progress, f"meshed {family} n={n}")
            meshed += meshed_level(family, n)

    rows = [_cut_row(c) for c in cut]
    summary = {
        "size": size,
        "peer": "ngsxfem",
        "available": True,
        "versions": {"ngsolve": ngsolve.__version__, "xfem": _xfem_version()},
        "problem": {"box": BOX, "torus": {"R": 1.0, "r": 0.5}, "tau_f": TAU_F, "face_h_power": 0, "error_quadrature_order": ORDER,
                    "shift": SHIFT.tolist(), "eps": EPS},
        "solvers": {"cutfem": "DirectSolver on the diagonally scaled matrix: LAPACK banded Cholesky after RCM (SuperLU for wide bands)",
                    "ngsxfem": "NGSolve sparsecholesky; solve_superlu: the NGSolve matrix through cutfem's DirectSolver"},
        "threads": "NGSolve without TaskManager (one thread); cutfem numpy/scipy",
        "cut": cut,
        "table": rows,
        "meshed": meshed,
    }
    save_json(out, NAME, summary)
    save_csv(out, NAME, rows)
    save_csv(out, f"{NAME}_meshed", meshed)
    _plot(out, rows, meshed)
    return {"size": size, "table": rows, "meshed": [r for r in meshed if r["method"] == "stabilized"]}


def _xfem_version():
    try:
        from importlib.metadata import version

        return version("xfem")
    except Exception:
        return None


@figure_style
def _plot(out, rows, meshed):
    from matplotlib.ticker import NullFormatter

    from cutfem.runs.convergence import new_figure

    fig, axes = new_figure(PAGE_WIDTH, 5.6, nrows=2, ncols=2)
    ax = axes[0, 0]
    for variant, mk in (("paper", "o"), ("shifted", "s")):
        sel = sorted((r for r in rows if r["variant"] == variant), key=lambda r: r["active_tets"])
        if not sel:
            continue
        ls = "-" if variant == "paper" else ":"
        ax.loglog([r["active_tets"] for r in sel], [r["time_cutfem"] for r in sel], marker=mk, color="C0", ls=ls,
                  label=f"cutfem ({variant})")
        ng = [r for r in sel if r["time_ngsxfem"] is not None]
        ax.loglog([r["active_tets"] for r in ng], [r["time_ngsxfem"] for r in ng], marker=mk, color="C3", ls=ls,
                  label=f"ngsxfem, 1 thread ({variant})")
        tm = [r for r in sel if r.get("time_ngsxfem_taskmanager") is not None]
        if tm:
            ax.loglog([r["active_tets"] for r in tm], [r["time_ngsxfem_taskmanager"] for r in tm], marker=mk, color="C1", ls=ls, mfc="none",
                      label=f"ngsxfem, TaskManager ({variant})")
        au = [r for r in sel if r.get("time_cutfem_auto") is not None]
        if au:
            ax.loglog([r["active_tets"] for r in au], [r["time_cutfem_auto"] for r in au], marker=mk, color="C2", ls="none", mfc="none",
                      label=f"cutfem, default solver ({variant})")
    ax.set_xlabel("active tets")
    ax.set_ylabel("wall time, end to end [s]")
    ax.set_title("cut torus: time (mesh, level set, cut, assembly, solve, error)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()

    ax = axes[0, 1]
    ax2 = ax.twinx()
    for variant, mk in (("paper", "o"), ("shifted", "s")):
        sel = sorted((r for r in rows if r["variant"] == variant), key=lambda r: r["spacing"])
        if not sel:
            continue
        ax.loglog([r["spacing"] for r in sel], [r["error_cutfem"] for r in sel], marker=mk, color="C0", ms=9, mfc="none",
                  ls="-" if variant == "paper" else ":", label=f"cutfem ({variant})")
        ng = [r for r in sel if r["error_ngsxfem"] is not None]
        ax.loglog([r["spacing"] for r in ng], [r["error_ngsxfem"] for r in ng], marker="x", color="C3", ls="none",
                  label=f"ngsxfem ({variant})")
        ax2.semilogy([r["spacing"] for r in ng], [max(r["rel_diff"], 1e-16) for r in ng], marker=mk, color="0.5", ls="--",
                     label=f"rel. difference ({variant})")
        same = [r for r in ng if r.get("rel_diff_cutfem_order") is not None]
        if same:
            ax2.semilogy([r["spacing"] for r in same], [max(r["rel_diff_cutfem_order"], 1e-16) for r in same], marker=mk, color="C4",
                         ls="none", mfc="none", label=f"rel. difference, cutfem's vertex order ({variant})")
        eps = [r for r in ng if r.get("rel_diff+eps") is not None]
        if eps:
            ax2.semilogy([r["spacing"] for r in eps], [r["rel_diff+eps"] for r in eps], marker="^", color="C2", ls="none",
                         label="rel. difference, ngsxfem zeros -> +eps")
    ax2.axhline(5e-4, color="0.7", lw=0.8)  # 3 significant digits
    ax2.set_ylim(1e-16, 1)
    ax.set_xscale("log")
    ax.set_xlabel("background spacing")
    ax.set_ylabel(r"$\|H^e - H_h\|_{L^2(S_h)}$")
    ax2.set_ylabel("relative difference of the errors (grey line: 3 digits)")
    ax.set_title("cut torus: error agreement")
    ax.grid(True, which="both", alpha=0.3)
    lines = ax.get_legend_handles_labels()
    lines2 = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + lines2[0], lines[1] + lines2[1], loc="lower right")

    for col, (key, ylabel, title) in enumerate((
        ("discrete_error", r"$\|\pi_h H - H_h\|_{S_h}$", "meshed torus: cotangent + lumped mass vs stabilized"),
        ("seconds", "wall time [s] (formula / assembly + solve)", "meshed torus: time"),
    )):
        ax = axes[1, col]
        for j, family in enumerate(FAMILIES):
            for method, mk in (("cotan-voronoi", "v"), ("stabilized", "o")):
                sel = [r for r in meshed if r["family"] == family and r["method"] == method]
                x = [r["h"] for r in sel] if col == 0 else [r["nodes"] for r in sel]
                ax.loglog(x, [r[key] for r in sel], marker=mk, color=f"C{j}", ls="-" if method == "stabilized" else "--",
                          label=f"{method}, {family}")
        ax.set_xlabel(r"$h = N^{-1/2}$" if col == 0 else "surface nodes N")
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    for ax in axes.ravel():
        ax.xaxis.set_minor_formatter(NullFormatter())
    save_figure(fig, out, NAME)


PROBLEMS = ("mean-curvature", "poisson", "both")


def main(argv=None) -> int:
    """``python -m cutfem.studies.peers [--problem mean-curvature|poisson|both]`` plus the usual
    study options (``--out``, the size flags).  Default: the mean curvature comparison."""
    import argparse

    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--problem", default="mean-curvature", choices=PROBLEMS,
                   help="which cut problem to compare with ngsxfem (default mean-curvature)")

    def run_selected(out, size, progress, problem):
        runners = {"mean-curvature": [run], "poisson": [run_poisson], "both": [run, run_poisson]}[problem]
        return [r(out, size, progress) for r in runners]

    return study_main(run_selected, NAME, p)(argv)


if __name__ == "__main__":
    raise SystemExit(main())
