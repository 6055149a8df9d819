"""The peer's side of the comparisons: ngsxfem (NGSolve + xfem) scripts for the cut problems,
run on cutfem's own tets (the comparisons and their tables: :mod:`cutfem.studies.peers`).

The cut mean curvature problem (docs/math.md §3, §6.3)
-----------------------------------------------------
Both codes solve, on the paper's box [-1.6,1.6]^2 x [-0.6,0.6] with the torus R = 1, r = 1/2:

* the same tetrahedra: the NGSolve mesh is built from cutfem's :class:`~cutfem.geometry.box.StructuredBox`
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

Fictitious-domain Poisson (docs/math.md §8)
-------------------------------------------
:func:`ngsxfem_poisson` solves ``cutfem.run("poisson-cut")``'s problem on the same tets, with the
same snapped P1 level set (zeros -> +EPS and the collapsed tets not counted as cut, as above), h_T
from netgen's element table and h_F from the facet normal (:func:`kuhn_face_h`: exact on a Kuhn
lattice, where NGSolve offers no longest edge of a facet), the inside of the level set through
:class:`NegSide`.

Stokes in the cut ball (docs/math.md §12)
-----------------------------------------
:func:`ngsxfem_stokes` solves ``cutfem.run("stokes-cut")``'s problem on the same tets and level set,
term by term (its docstring lists them), with the mean-value multiplier bordered onto the assembled
matrix (:func:`bordered`) and NGSolve's MINRES with a factorized block-diagonal preconditioner.
"""

from __future__ import annotations

import gc
import math
import time
from pathlib import Path

import numpy as np

from cutfem.geometry.cut import snapped_nodal_values
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.numbering import TET_FACES
from cutfem.problems.common import background_for
from cutfem.solvers.solve import DirectSolver

INSTALL = 'install with pip install -e ".[peers]"'
TAU_F = 0.1
ORDER = 4
EPS = 1e-14
#: the Poisson comparison: unit ball in cutfem's default structured box, its default penalties
POISSON_GAMMA = 10.0
POISSON_GAMMA_G = 0.1


def peer_missing() -> str | None:
    """None when ngsolve and xfem import, else the import error message."""
    try:
        import ngsolve  # noqa: F401
        import xfem  # noqa: F401
    except Exception as exc:  # ImportError, or a broken binary install
        return f"{type(exc).__name__}: {exc}"
    return None


def peer_versions() -> dict:
    """{"ngsolve": its version, "xfem": its version (None when the metadata says nothing)} of the
    installed peer."""
    import ngsolve

    return {"ngsolve": ngsolve.__version__, "xfem": _xfem_version()}


def _xfem_version():
    try:
        from importlib.metadata import version

        return version("xfem")
    except Exception:
        return None


def kuhn_boundary_triangles(box) -> np.ndarray:
    """(k, 3) node ids of the boundary triangles of a StructuredBox, outward oriented (right-hand
    rule), found among the Kuhn tets of the boundary cells only."""
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
    split quadrilateral pieces (see :mod:`cutfem.studies.peers`).
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


class NegSide:
    """The inside {phi_h < 0} of cutfem's snapped P1 level set on an :class:`NgBackground`, as the
    bulk problems see it in ngsxfem: the level set GridFunction (zeros -> +EPS), the tets that meet
    it (``hasneg``), the cut tets without those whose piece collapses under cutfem's zero rule
    (``cut``, :func:`collapsed_tets`: their pieces of Gamma_h have area O(EPS)), the ghost facets
    (interior facets between a HASNEG tet and a cut one, cutfem's ``ghost_facets(NEG)``) and h_T
    (the longest edge of each tet, an order-0 L2 GridFunction).  Fills the stages ``levelset``
    (nodal values and GridFunction) and ``cut`` (the rest) of the timer dict ``T``."""

    def __init__(self, background, levelset, T):
        import ngsolve as ngs
        from ngsolve import H1, L2, GridFunction
        from xfem import HASNEG, IF, CutInfo, GetFacetsWithNeighborTypes

        mesh = background.mesh
        t0 = time.perf_counter()
        self.snapped = cutfem_nodal_values(background.box, levelset)
        values = self.snapped.copy()
        values[values == 0] = EPS
        self.lset = GridFunction(H1(mesh, order=1))
        self.lset.vec.FV().NumPy()[:] = values
        T["levelset"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        ci = CutInfo(mesh, self.lset)
        self.hasneg = ci.GetElementsOfType(HASNEG)
        self.cut = ngs.BitArray(ci.GetElementsOfType(IF))
        self.dropped = collapsed_tets(background.box, self.snapped)
        for k in self.dropped.tolist():  # only around the nodes on the surface
            self.cut.Clear(k)
        self.ghost = GetFacetsWithNeighborTypes(mesh, a=self.hasneg, b=self.cut, bnd_val_a=False, bnd_val_b=False, use_and=True)
        self.hT = GridFunction(L2(mesh, order=0))
        self.hT.vec.FV().NumPy()[:] = element_longest_edges(mesh)
        T["cut"] = time.perf_counter() - t0
        self.mesh = mesh

    def sizes(self) -> dict:
        """The sizes a record carries: active (HASNEG) tets, cut tets, ghost faces, zero nodes, the
        collapsed tets dropped from the cut ones, background nodes and tets."""
        return {"active_tets": int(self.hasneg.NumSet()), "cut_tets": int(self.cut.NumSet()), "ghost_faces": int(self.ghost.NumSet()),
                "zero_nodes": int(np.sum(self.snapped == 0)), "dropped_collapsed_tets": int(self.dropped.size),
                "background_nodes": int(self.mesh.nv), "background_tets": int(self.mesh.ne)}


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
    from ngsolve import H1, GridFunction, InnerProduct, Integrate, LinearForm, grad, specialcf, sqrt
    from xfem import IF, NEG, GetDofsOfElements, RestrictedBilinearForm, dCut

    levelset = Sphere() if levelset is None else levelset
    T = {}
    if background is None:
        background = NgBackground(spacing, levelset)
    mesh = background.mesh
    side = NegSide(background, levelset, T)
    lset, hasneg, cut, ghost, hT = side.lset, side.hasneg, side.cut, side.ghost, side.hT
    t0 = time.perf_counter()
    Vf = H1(mesh, order=1, dgjumps=True)
    V = ngs.Compress(Vf, GetDofsOfElements(Vf, hasneg))
    T["cut"] += time.perf_counter() - t0

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
        **side.sizes(),
        "solver": inverse,
        "solver_iterations": int(iterations),
        "time": T,
        "total": sum(T.values()),
        **extra,
    }


#: the Stokes comparison: cutfem's ``stokes-cut`` defaults (unit ball in its default structured box)
STOKES_PARAMS = {"nu": 1.0, "gamma": 20.0, "gamma_u": 0.1, "gamma_p": 0.1, "beta": 0.05}
#: NGSolve's MINRES stops at this relative residual in the preconditioner's norm (cutfem's: in the 2-norm)
MINRES_TOL = 1e-8


def stokes_exact_cf(nu=1.0):
    """(u, grad u, p, f) of cutfem's manufactured Stokes solution as NGSolve CoefficientFunctions:
    u = curl A, A = (sin y sin z, sin z sin x, sin x sin y), which is
    u = (sin x (cos y - cos z), sin y (cos z - cos x), sin z (cos x - cos y)) with -Lap u = 2 u;
    p = x y z + x^2 - y^2; f = -nu Lap u + grad p = 2 nu u + (y z + 2 x, x z - 2 y, x y).
    (grad u)_ij = d u_i / d x_j, NGSolve's ``grad`` of a vector field."""
    from ngsolve import CF, cos, sin, x, y, z

    sx, sy, sz, cx, cy, cz = sin(x), sin(y), sin(z), cos(x), cos(y), cos(z)
    u = CF((sx * (cy - cz), sy * (cz - cx), sz * (cx - cy)))
    grad_u = CF((cx * (cy - cz), -sx * sy, sx * sz,
                 sx * sy, cy * (cz - cx), -sy * sz,
                 -sz * sx, sz * sy, cz * (cx - cy)), dims=(3, 3))
    p = x * y * z + x * x - y * y
    f = 2 * nu * u + CF((y * z + 2 * x, x * z - 2 * y, x * y))
    return u, grad_u, p, f


def _coo(mat, zeros=True):
    """(rows, cols, values) of the entries of a symmetric NGSolve sparse matrix stored whole or as its
    lower triangle; without the stored zeros when ``zeros`` is False."""
    rows, cols, vals = (np.array(t) for t in mat.COO())
    if not zeros:
        nonzero = vals != 0
        rows, cols, vals = rows[nonzero], cols[nonzero], vals[nonzero]
    if np.all(rows >= cols):  # the lower triangle only: mirror the off-diagonal entries
        off = rows > cols
        rows, cols, vals = np.concatenate([rows, cols[off]]), np.concatenate([cols, rows[off]]), np.concatenate([vals, vals[off]])
    return rows, cols, vals


def bordered(mat, c):
    """The NGSolve sparse matrix [[K, c], [c^T, 0]] of the symmetric ``mat`` (K) bordered by the
    vector ``c``: the Lagrange multiplier of the constraint c^T x = 0, built by NGSolve's own COO
    constructor (full storage)."""
    import ngsolve as ngs

    rows, cols, vals = _coo(mat)
    n = mat.height
    cv = np.array(c.FV().NumPy())
    nz = np.flatnonzero(cv)
    rows = np.concatenate([rows, nz, np.full(nz.size, n)]).astype(np.int64)
    cols = np.concatenate([cols, np.full(nz.size, n), nz]).astype(np.int64)
    vals = np.concatenate([vals, cv[nz], cv[nz]])
    return ngs.la.SparseMatrixd.CreateFromCOO(rows, cols, vals, n + 1, n + 1)


def _block_preconditioner(K, S, n_velocity, multiplier):
    """The block-diagonal preconditioner diag(A, S~, m) of the bordered Stokes matrix ``K`` as one
    NGSolve sparse matrix: A the velocity block of K (its first ``n_velocity`` unknowns), S~ the
    pressure mass (the assembled ``S``, already scaled by 1/nu) minus K's pressure block (+ the
    pressure stabilizations), and m = ``multiplier`` the multiplier's Schur number."""
    import ngsolve as ngs

    # without the stored zeros: the graph of a compound space couples every pair of unknowns of a tet,
    # the velocity components among them (exact zeros), which would fill the factorization of A, whose
    # components decouple.  The direct solves of the whole matrix keep them: their equal patterns
    # make the supernodes of its factorization (several times faster with them)
    rk, ck, vk = _coo(K, zeros=False)
    keep = (rk < K.height - 1) & (ck < K.height - 1) & ((rk < n_velocity) == (ck < n_velocity))
    vk = np.where(rk < n_velocity, vk, -vk)
    rs, cs, vs = _coo(S, zeros=False)
    rows = np.concatenate([rk[keep], rs, [K.height - 1]]).astype(np.int64)
    cols = np.concatenate([ck[keep], cs, [K.height - 1]]).astype(np.int64)
    vals = np.concatenate([vk[keep], vs, [multiplier]])
    return ngs.la.SparseMatrixd.CreateFromCOO(rows, cols, vals, K.height, K.height)


def ngsxfem_stokes(spacing, levelset=None, nu=STOKES_PARAMS["nu"], gamma=STOKES_PARAMS["gamma"], gamma_u=STOKES_PARAMS["gamma_u"],
                   gamma_p=STOKES_PARAMS["gamma_p"], beta=STOKES_PARAMS["beta"], inverse="minres", background=None) -> dict:
    """P1-P1 Stokes in the cut ball (``cutfem.run("stokes-cut")``, docs/math.md §12) with ngsxfem on
    cutfem's structured background.

    The same discrete problem: velocity ``VectorH1`` and pressure ``H1`` of order 1, each compressed
    to the dofs of the HASNEG tets (:class:`NegSide`), in one space with ``dgjumps=True``; the
    symmetric form

        nu (grad u, grad v) - (div v, p) - (div u, q) - (beta / nu) h_T^2 (grad p, grad q)   on Omega_h
        + nu (-(grad u n, v) - (grad v n, u) + (gamma / h_T) (u, v)) + (v . n, p) + (u . n, q)   on Gamma_h
        + nu gamma_u h_F ([grad u n_F], [grad v n_F]) - (gamma_p / nu) h_F^3 ([n_F . grad p], [n_F . grad q])   on the ghost facets

    (the Brezzi-Pitkaranta term over the cut part of each tet, as cutfem's), bordered by the mean
    value (q, 1)_Omega_h as a Lagrange multiplier (:func:`bordered`), and the load
    (f, v)_Omega_h + nu (g, -grad v n + (gamma / h_T) v)_Gamma + (g . n, q)_Gamma with g = u.
    ngsxfem's own multiplier, a ``NumberSpace`` in the same space, gives the same solution, but
    beside the ghost facets the first assembly on such a space is two orders of magnitude slower
    (a table of the facet couplings of its global unknown), so the matrix is bordered after
    assembly.  Each term is its own compiled integrator: several times faster than one sum per
    measure (NGSolve's C++ code generation, ``realcompile``, costs more to compile than it saves).
    Quadrature: order 2 for the form (exact for P1), order 4 for the loads and the errors (cutfem:
    degree 4).  The pressure error is against p minus its mean over Omega_h (the discrete pressure
    has mean zero there).

    ``inverse``: "minres" (NGSolve's MINRES to :data:`MINRES_TOL` with the block-diagonal
    preconditioner of :func:`_block_preconditioner` factorized by its sparse Cholesky: exact block
    solves, about 30 iterations) or an NGSolve direct inverse of the whole matrix ("sparsecholesky",
    "umfpack", "pardiso" where MKL is installed).  Returns the errors, sizes, iterations, the
    relative residual of the bordered system and the stage times (mesh, levelset, cut, assembly,
    solve, errors)."""
    import ngsolve as ngs
    from ngsolve import H1, GridFunction, InnerProduct, Integrate, LinearForm, VectorH1, div, grad, specialcf, sqrt
    from xfem import IF, NEG, GetDofsOfElements, RestrictedBilinearForm, dCut

    levelset = Sphere() if levelset is None else levelset
    T = {}
    if background is None:
        background = NgBackground(spacing, levelset)
    mesh = background.mesh
    T["mesh"] = background.seconds
    side = NegSide(background, levelset, T)
    lset, hasneg, cut, ghost, hT = side.lset, side.hasneg, side.cut, side.ghost, side.hT
    t0 = time.perf_counter()
    Vf, Qf = VectorH1(mesh, order=1), H1(mesh, order=1)
    W = ngs.FESpace([ngs.Compress(Vf, GetDofsOfElements(Vf, hasneg)), ngs.Compress(Qf, GetDofsOfElements(Qf, hasneg))], dgjumps=True)
    T["cut"] += time.perf_counter() - t0

    t0 = time.perf_counter()
    u_ex, grad_ex, p_ex, f = stokes_exact_cf(nu)
    (u, p), (v, q) = W.TnT()
    g = grad(lset)
    n = g / sqrt(InnerProduct(g, g))
    dxn = dCut(levelset=lset, domain_type=NEG, definedonelements=hasneg, order=2)
    dxn4 = dCut(levelset=lset, domain_type=NEG, definedonelements=hasneg, order=4)
    ds = dCut(levelset=lset, domain_type=IF, definedonelements=cut, order=2)
    ds4 = dCut(levelset=lset, domain_type=IF, definedonelements=cut, order=4)
    dw = ngs.dx(skeleton=True, definedonelements=ghost)
    nF, hF = specialcf.normal(3), kuhn_face_h(spacing)
    du, dv = (grad(u) - grad(u.Other())) * nF, (grad(v) - grad(v.Other())) * nF
    dp, dq = InnerProduct(grad(p) - grad(p.Other()), nF), InnerProduct(grad(q) - grad(q.Other()), nF)
    terms = [(nu * InnerProduct(grad(u), grad(v)), dxn), (-div(v) * p - div(u) * q, dxn),
             (-beta / nu * hT * hT * InnerProduct(grad(p), grad(q)), dxn),
             (nu * (-InnerProduct(grad(u) * n, v) - InnerProduct(grad(v) * n, u) + gamma / hT * InnerProduct(u, v)), ds),
             (InnerProduct(v, n) * p + InnerProduct(u, n) * q, ds),
             (nu * gamma_u * hF * InnerProduct(du, dv), dw), (-gamma_p / nu * hF ** 3 * dp * dq, dw)]
    a = RestrictedBilinearForm(W, element_restriction=hasneg, facet_restriction=ghost, symmetric=True, check_unused=False)
    for cf, measure in terms:  # one integrator a term, each compiled: 4 times faster than one sum a measure
        a += cf.Compile() * measure
    a.Assemble()
    b = LinearForm(W)
    b += InnerProduct(f, v) * dxn4
    b += (nu * InnerProduct(u_ex, -grad(v) * n + gamma / hT * v) + InnerProduct(u_ex, n) * q) * ds4
    b.Assemble()
    mean = LinearForm(W)
    mean += q * dxn
    mean.Assemble()
    K = bordered(a.mat, mean.vec)
    rhs = K.CreateColVector()
    rhs.FV().NumPy()[:] = np.append(b.vec.FV().NumPy(), 0.0)
    if inverse == "minres":
        m = RestrictedBilinearForm(W, element_restriction=hasneg, symmetric=True, check_unused=False)
        m += (1 / nu) * p * q * dxn
        m.Assemble()
    T["assembly"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    sol = K.CreateColVector()
    iterations = 0
    if inverse == "minres":
        # S~ 1 = (1/nu) c exactly (the stabilizations vanish on constants): the multiplier's Schur number c^T S~^-1 c = nu |Omega_h|
        P = _block_preconditioner(K, m.mat, W.components[0].ndof, nu * float(np.sum(mean.vec.FV().NumPy())))
        solver = ngs.solvers.MinResSolver(K, P.Inverse(inverse="sparsecholesky"), tol=MINRES_TOL, maxiter=1000)
        sol.data = solver * rhs
        iterations = solver.iterations
    else:
        sol.data = K.Inverse(inverse=inverse) * rhs
    x = GridFunction(W)
    x.vec.FV().NumPy()[:] = sol.FV().NumPy()[:-1]
    T["solve"] = time.perf_counter() - t0
    residual = rhs.CreateVector()
    residual.data = rhs - K * sol
    residual = float(residual.Norm() / rhs.Norm())

    t0 = time.perf_counter()
    uh, ph = x.components[0], x.components[1]
    volume = Integrate(ngs.CF(1.0) * dxn, mesh)
    p0 = p_ex - Integrate(p_ex * dxn4, mesh) / volume
    eu, eg, ep = uh - u_ex, grad(uh) - grad_ex, ph - p0
    l2u = math.sqrt(Integrate(InnerProduct(eu, eu) * dxn4, mesh))
    h1u = math.sqrt(Integrate(InnerProduct(eg, eg) * dxn4, mesh))
    l2p = math.sqrt(Integrate(ep * ep * dxn4, mesh))
    T["errors"] = time.perf_counter() - t0
    return {
        "l2_error_velocity": l2u,
        "h1_error_velocity": h1u,
        "l2_error_pressure": l2p,
        "volume": volume,
        "pressure_mean": Integrate(ph * dxn4, mesh) / volume,
        "dofs": int(W.ndof) + 1,
        **side.sizes(),
        "solver": inverse,
        "solver_iterations": int(iterations),
        "residual": residual,
        "time": T,
        "total": sum(T.values()),
    }
