"""The exact implementations of the built-in terms (:mod:`cutfem.fem.terms`) for P1.

P1 functions are linear on each simplex, so every built-in term has a closed form there: the mass
matrix of a simplex from its vertex values (|T| / ((k)(k+1)) (I + 1 1^T)), the stiffness and the
jumps from constant gradients, the moments of a piece of S_h from its triangles.  They are summed
as Gram products E^T E (:func:`cutfem.fem.assembly.gram`: exactly symmetric), into the lattice
slots of a structured box (:class:`cutfem.fem.assembly.LatticeSum`) or, on a triangulated surface,
per node, edge and pair of vertices opposite an edge (:class:`cutfem.fem.assembly.PairSum`), each
times its coefficient in the form (``scale``).  The loads are quadratures of their data, block by
block of cells (:func:`_point_load`).  The quadrature of the terms' integrands gives the same
matrices and vectors to round-off (tested).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from . import assembly as _assembly
from . import element_kernels
from .assembly import assemble_vector, gram, gram_sum
from ..geometry.markers import CUT
from ..geometry.numbering import TET_EDGES, index_dtype
from .pointwise import _point_values


def _sqrt_reference_mass(k: int) -> np.ndarray:
    """R (k, k) with R^T R = (I + 1 1^T) / ((k)(k+1)): the P1 mass matrix of a simplex of unit
    measure with k vertices (triangle: 1/12 (1 + delta_ij), tetrahedron: 1/20 (1 + delta_ij))."""
    ref = (np.eye(k) + np.ones((k, k))) / (k * (k + 1))
    w, Q = np.linalg.eigh(ref)
    return np.sqrt(w)[:, None] * Q.T


def _simplex_mass(space, vertices, elements, sizes):
    """Gram rows of the exact mass matrix over simplices (triangles or tets) lying in the field's
    ``elements``, with measures ``sizes``."""
    lam = space.basis_at(vertices, elements)  # (m, k_vertices, k_dofs)
    R = _sqrt_reference_mass(vertices.shape[1])
    rows = R @ lam
    del lam
    rows *= np.sqrt(sizes)[:, None, None]
    k = rows.shape[2]
    dofs = np.repeat(_compact(space.element_dofs[elements], space.n_dofs), rows.shape[1], axis=0)
    return gram(dofs, rows.reshape(-1, k), space.n_dofs, overwrite=True)


def _compact(dofs, n):
    """dofs as int32 when the numbers fit (no copy when they already are): the Gram rows repeat
    them, int32 halves that copy."""
    return dofs.astype(index_dtype(n), copy=False)


def _gradient_matrix(space, grads_of, weights, elements=None):
    """The Gram matrix of the rows sqrt(weights) * G[:, :, d], d = 0, 1, 2, with G = grads_of(cells)
    (b, k, 3) for a slice of the m = len(weights) cells, on the field's ``elements`` (all of them by
    default): sum_T weights_T G_T G_T^T, built and multiplied a block of elements at a time
    (:func:`~cutfem.fem.assembly.gram_sum`: the rows of 1.6 million tets, with their transpose, took
    0.6 GB at once; the gradients themselves are asked for one block at a time)."""
    k, m = space.element_dofs.shape[1], len(weights)
    step = max(_assembly.GRAM_ROWS // 3, 1)

    def blocks():
        for start in range(0, m, step):
            cells = slice(start, start + step)
            rows = (grads_of(cells) * np.sqrt(weights[cells])[:, None, None]).transpose(0, 2, 1).reshape(-1, k)  # (3 b, k)
            dofs = space.element_dofs[cells] if elements is None else space.element_dofs[elements[cells]]
            yield np.repeat(_compact(dofs, space.n_dofs), 3, axis=0), rows

    return gram_sum(blocks(), space.n_dofs)


def _kuhn_stiffness(space, volumes, into, scale=1.0):
    """sum_T |T ∩ side| G_T G_T^T over all the tets of a structured box's element set, times ``scale`` into ``into``
    (:class:`~cutfem.fem.assembly.LatticeSum`): the gradients of Kuhn tet l are KUHN_GRADIENTS[l] /
    spacing (:attr:`~cutfem.geometry.mesh.StructuredBox.gradient_table`), so the products G_i . G_j form a
    (6, 4, 4) table and each tet's entries are a row of it times its volume."""
    G = space.elements.background.gradient_table
    D = np.einsum("lid,ljd->lij", G, G)
    edges, diagonal = D[:, TET_EDGES[:, 0], TET_EDGES[:, 1]], D[:, np.arange(4), np.arange(4)]
    into.add_elements(space.element_dofs, edges, diagonal, types=space.elements.kuhn_types, weights=volumes, scale=scale)


def _kuhn_volume_mass(space, measure, into, scale=1.0):
    """The volume mass matrix over the cells of a side (or of whole tets) of a structured box's
    element set: the whole elements' M_T = |T|/20 (1 + delta_ij) summed per lattice edge (times ``scale``) into
    ``into`` (:class:`~cutfem.fem.assembly.LatticeSum`: no basis values, no Gram product); returns the
    sub-tets of the cut elements by :func:`_simplex_mass` (None if there are none)."""
    w = measure.whole_cells
    into.add_elements(space.element_dofs, np.full(6, 1.0 / 20.0), np.full(4, 1.0 / 10.0), weights=space.elements.volumes,
                      elements=measure.whole_elements, scale=scale)
    if measure.n_cells > w:
        sub, parent = measure.sub_tets
        return _simplex_mass(space, sub, parent, measure.sub_volumes)
    return None


def _piece_mass(space, into=None, scale=1.0):
    """The exact surface mass matrix of a cut space on its own cut tets: into ``into`` (a
    :class:`~cutfem.fem.assembly.LatticeSum`, times ``scale``) triangle by triangle of S_h
    (:meth:`~cutfem.fem.assembly.LatticeSum.add_pieces`: no per-tet arrays, 112 bytes a cut tet), else
    the element matrices M_K = int_{S_K} lambda_i lambda_j of :func:`_piece_moments` summed by
    :func:`_element_symmetric`.  The same matrix as the triangle route (:func:`_simplex_mass`) to
    round-off either way (tested)."""
    if into is not None:
        c = space.cut
        table, types = space.gradient_lookup()
        into.add_pieces(c.vertices, c.triangles, c.triangle_tets, c.triangle_areas, space.dof_points, space.element_dofs,
                        table, types, space.element_dofs, scale)
        return None
    edges, diagonal, _ = _piece_moments(space.cut)
    return _element_symmetric(space, slice(None), edges, diagonal)


def _piece_moments(cut):
    """(edges (m, 6), diagonal (m, 4), integrals (m, 4)) for the m cut tets (the element set CUT, in
    its order): the exact piece mass matrices M_K by their entries on the local edges
    (:data:`~cutfem.geometry.numbering.TET_EDGES`) and diagonal, and int_{S_K} lambda_i; one compiled pass over
    the triangles of S_h (:func:`cutfem.fem.element_kernels.piece_moments`)."""

    es = cut.elements(CUT)
    table, types = es.gradient_lookup()
    return element_kernels.piece_moments(cut.vertices, cut.triangles, cut.triangle_tets, cut.triangle_areas, es.points, es.tets,
                                 table, types)


def _element_symmetric(space, el, edges, diagonal, into=None, scale=1.0):
    """sum_K A_K of symmetric 4 x 4 element matrices on the field's elements ``el`` (an index or a
    slice), given by their entries on the local edges ``edges`` (m, 6) (:data:`~cutfem.geometry.numbering.TET_EDGES`
    order) and their ``diagonal`` (m, 4): added times ``scale`` into ``into`` (a
    :class:`~cutfem.fem.assembly.LatticeSum` of a structured box: no sort; returns None), or as one COO matrix when ``into`` is None.
    Exactly symmetric either way."""
    dofs = space.element_dofs[el]
    if into is not None:
        into.add_elements(dofs, edges, diagonal, scale=scale)
        return None
    i, j = TET_EDGES[:, 0], TET_EDGES[:, 1]
    rows = np.concatenate([dofs[:, i].ravel(), dofs[:, j].ravel(), dofs.ravel()])
    cols = np.concatenate([dofs[:, j].ravel(), dofs[:, i].ravel(), dofs.ravel()])
    values = np.concatenate([edges.ravel(), edges.ravel(), diagonal.ravel()])
    A = sp.coo_matrix((values, (rows, cols)), shape=(space.n_dofs, space.n_dofs)).tocsr()
    return (0.5 * (A + A.T)).tocsr()  # the sums of duplicates run in different orders for (i, j) and (j, i)


def _kuhn_tangential_stiffness(space, measure, into, scale=1.0):
    """sum_K |K| (P_h G)(P_h G)^T over the pieces of the cut tets of a structured box, times
    ``scale`` into ``into`` (:class:`~cutfem.fem.assembly.LatticeSum`).  G is the row of the tet's Kuhn type in the
    (6, 4, 3) gradient table, so with c = G n_h the entries are |K| (G_a . G_b - c_a c_b), per tet
    in one compiled pass (:func:`cutfem.fem.element_kernels.tangential_entries`): no (m, 4, 3) gradients and no
    sparse Gram product."""

    table, types = space.gradient_lookup()
    m = len(types)
    edges, diagonal = np.empty((m, 6)), np.empty((m, 4))
    element_kernels.tangential_entries(np.ascontiguousarray(table, dtype=float), np.ascontiguousarray(types),
                               np.ascontiguousarray(measure.normals, dtype=float),
                               np.ascontiguousarray(measure.piece_areas, dtype=float), edges, diagonal)
    into.add_elements(space.element_dofs, edges, diagonal, scale=scale)


def _point_load(space, measure, degree, f, what, local):
    """The vector of a load term on ``space``, block by block of ``measure``'s cells at quadrature
    ``degree``: fw = w_q f(x_q) (``f`` checked as ``what``: real, finite, (m, q) or (m, q, c)), then
    ``local(quad, elements, basis values, fw)`` -> (m, k) or (m, k, c) per cell, summed into the
    dofs; (n,) or (n, c), zeros when the measure has no cells."""
    out = None
    for _, quad in measure.blocks(degree):
        fx = _point_values(f, quad.points, what)
        fw = fx * (quad.weights if fx.ndim == 2 else quad.weights[..., None])
        el = space.local_elements(measure, quad.parent)
        values = local(quad, el, space.basis_on(measure, quad, el), fw)
        if out is None:
            out = np.zeros((space.n_dofs,) + values.shape[2:])
        assemble_vector(np.take(space.element_dofs, el, axis=0), values, space.n_dofs, out=out)
    return np.zeros(space.n_dofs) if out is None else out


def _jump_gram(space, pairs, normals_a, normals_b, sign_b, scale):
    """Gram matrix of the jumps c = (t_a . G_{K_a}, t_b . G_{K_b}), t_a = ``normals_a``, t_b = ``sign_b``
    ``normals_b`` (F, 3), weighted by ``scale`` (>= 0): one row per pair (K_a, K_b) = ``pairs`` of the
    field's elements on their dofs (shared dofs summed), by :func:`cutfem.fem.element_kernels.jump_rows`, a block
    of pairs at a time by sparse Gram products (:func:`~cutfem.fem.assembly.gram_sum`; the rows of the
    5.6 million interior faces of the cut torus at spacing 0.00625, with their dofs, took 0.5 GB at
    once).  Faces of a structured box go into lattice slots instead (:func:`cutfem.fem.terms.face_jump_penalty`)."""

    dofs = space.element_dofs  # read as they are; the rows' copies are int32 when the numbers fit
    index = index_dtype(space.n_dofs)
    table, types = space.gradient_lookup()
    k = dofs.shape[1]

    def blocks():
        for start in range(0, len(pairs), _assembly.GRAM_ROWS):
            f = slice(start, start + _assembly.GRAM_ROWS)
            p = np.ascontiguousarray(pairs[f])
            rows_dofs, rows = np.empty((len(p), 2 * k), dtype=index), np.empty((len(p), 2 * k))
            element_kernels.jump_rows(p, normals_a[f], normals_b[f], float(sign_b), np.ascontiguousarray(scale[f], dtype=float), dofs,
                              table, types, rows_dofs, rows)
            yield rows_dofs, rows

    return gram_sum(blocks(), space.n_dofs)


# ---------------------------------------------------------------------------------------------
# Closed forms on a triangulated surface (SurfaceP1Space).  On a flat triangle T with edge vectors
# e_k = x_{k+1} - x_k (indices mod 3) every P1 integral is a rational function of |T| and the dot
# products S_k = e_k . e_k, Q_k = e_k . e_{k+1} (SurfaceMesh.triangle_edge_dots).  Arrays of shape
# (M, 3) are indexed by the half-edge 3 t + k (local edge k of triangle t, from vertex k to k + 1,
# which is also the corner of vertex k); the half-edge after it in the triangle is the column
# rotated by one, X[:, _NEXT] (the edge penalty's passes are compiled).  Each matrix is a diagonal plus one
# value per pair of nodes, summed by cutfem.fem.assembly.PairSum and written straight into the cached
# CSR structure of the node graph or the edge stencil (cutfem.fem.assembly.SymmetricPattern): no
# quadrature, no sort, no sparse sum, exactly symmetric.  The quadrature
# routes give the same matrices to round-off (tested).
# ---------------------------------------------------------------------------------------------

_NEXT = [1, 2, 0]


def _meshed_mass(space, into, scale=1.0) -> None:
    """Exact P1 mass matrix of S_h, added times ``scale`` into ``into`` (:class:`~cutfem.fem.assembly.PairSum`):
    M_T = |T|/12 (I + 1 1^T), i.e.

        M_ii = sum_{T at i} |T| / 6,   M_ij = sum_{T at edge ij} |T| / 12.
    """
    areas = space.element_areas
    diagonal = np.bincount(space.element_dofs.reshape(-1), weights=np.repeat(areas / 6.0, 3), minlength=space.n_dofs)
    et = space.mesh.edge_triangles
    into.add(diagonal, (areas[et[:, 0]] + areas[et[:, 1]]) / 12.0, scale=scale)


def _meshed_stiffness(space):
    """P1 stiffness matrix of S_h (the cotangent formula in edge vectors), as (diagonal (n,), one
    value per edge (E,)) on the node graph:

        |T| grad lambda_i . grad lambda_j = e_{i+1} . e_{j+1} / (4 |T|),

    so vertex k of T adds S_{k+1} / (4|T|) to the diagonal and its local edge k, from vertex k to
    k + 1, adds Q_{k+1} / (4|T|) to that edge's entry.
    """
    S, Q = space.mesh.triangle_edge_dots
    quarter = 0.25 / space.element_areas[:, None]
    diagonal = np.bincount(space.element_dofs.reshape(-1), weights=(S[:, _NEXT] * quarter).reshape(-1), minlength=space.n_dofs)
    per_halfedge = (Q[:, _NEXT] * quarter).reshape(-1)
    h = space.mesh.edge_halfedges
    return diagonal, per_halfedge[h[:, 0]] + per_halfedge[h[:, 1]]


def _meshed_edge_penalty(space, h: float):
    """J_E of docs/math.md §3 on S_h in closed form: sum_E h |E| a a^T with a the jump coefficients,
    as (diagonal (n,), one value per edge (E,), one per pair of vertices opposite an edge (E,)),
    the pairs of :meth:`SurfaceP1Space.edge_stencil_pattern`.

    The outward conormal of triangle K at its edge k is t = e_k / |e_k| x n_K, and
    t . grad lambda_m = -e_k . e_{m+1} / (2 |K| |E|): at the start, the end and the opposite vertex
    of half-edge k,

        c_start = -Q_k / (2|K||E|),  c_end = -Q_{k-1} / (2|K||E|),  c_opp = -|E| / (2|K|)

    (e_{k-1} . e_k = e_k . e_{k+2}; the three sum to zero).  Edge E = [i, j] has the half-edges
    h1: i -> j in K1 (opposite vertex k) and its twin h2: j -> i in K2 (opposite l), so the jump
    [t_E . grad u] = a_i u_i + a_j u_j + a_k u_k + a_l u_l has a_i = c_start(h1) + c_end(h2),
    a_j = c_end(h1) + c_start(h2), a_k = c_opp(h1), a_l = c_opp(h2).  With b = sqrt(h |E|) a
    written per half-edge (b_start, b_end, b_opp), edge E adds b_x b_y to every pair {x, y} of its
    four nodes:

    * {i, j}: b_start(h1) b_end(h1); {k, l}: b_opp(h1) b_opp(h2)
      (:meth:`SurfaceP1Space.edge_stencil_pattern`);
    * the other two edges of each triangle: half-edge g gets b_end b_opp from the half-edge
      before it and b_opp b_start from the one after it;
    * the diagonal: corner g (vertex k of K, where half-edge g starts) gets b_start(g)^2 from the
      edge leaving it and b_opp^2 from the edge opposite to it, the half-edge after g.
    """

    mesh = space.mesh
    S, Q = mesh.triangle_edge_dots
    h1, h2 = mesh.edge_halfedges.T
    return element_kernels.meshed_edge_penalty(space.element_dofs, S, Q, space.element_areas, float(h), np.ascontiguousarray(h1),
                                       np.ascontiguousarray(h2), space.n_dofs)


# ---------------------------------------------------------------------------------------------
# Linear elasticity on a vector field (VectorSpace of a scalar space V, n = V.n_dofs, component-major).
# For u = phi_a e_k, v = phi_b e_l with constant gradients g on a tet, 2 mu eps(u) : eps(v) + lam div u div v
# is mu delta_kl g_a . g_b + mu (g_b)_k (g_a)_l + lam (g_b)_l (g_a)_k: the element matrix K[(l, b), (k, a)].
# ---------------------------------------------------------------------------------------------


def _elasticity_table(G, mu, lam):
    """Element matrices (L, 4, 4, 3, 3) of 2 mu eps : eps + lam div div per unit volume for the
    gradients G (L, 4, 3): [r, i, j, l, k] = mu delta_lk G_i . G_j + mu G_ik G_jl + lam G_il G_jk
    (row: node i, component l; column: node j, component k)."""
    dots = np.einsum("rid,rjd->rij", G, G)
    out = mu * np.einsum("rik,rjl->rijlk", G, G) + lam * np.einsum("ril,rjk->rijlk", G, G)
    out += mu * dots[..., None, None] * np.eye(3)
    return out


def _kuhn_elasticity(space, volumes, mu, lam, into, scale=1.0):
    """sum_T |T ∩ side| (2 mu eps : eps + lam div div) over all the tets of a structured box's
    element set into the 3 x 3 blocks of ``into`` (:class:`~cutfem.fem.assembly.VectorSum`), times
    ``scale``: the gradients of Kuhn tet type r are a row of the (6, 4, 3) table
    (:attr:`~cutfem.geometry.box.StructuredBox.gradient_table`), so the element matrices are a (6, 4,
    4, 3, 3) table times the volumes (:func:`cutfem.fem.assembly_kernels.lattice_add_blocks`)."""
    V = space.scalar
    table = _elasticity_table(V.elements.background.gradient_table, mu, lam)
    into.add_block_elements(V.element_dofs, table, types=V.elements.kuhn_types, weights=volumes, scale=scale)


def _elasticity_gram(space, grads_of, weights, mu, lam, elements=None):
    """The elasticity matrix as a Gram product E^T E, where E has per tet T (gradients G =
    grads_of(cells), weight w = ``weights[T]``) the rows of 2 mu eps : eps + lam div div:
    sqrt(2 mu w) eps_ii (4 entries, component i), sqrt(mu w) (d_j u_i + d_i u_j) for i < j (8
    entries), sqrt(lam w) div u (12 entries); a block of tets at a time
    (:func:`~cutfem.fem.assembly.gram_sum`).  Exactly symmetric; for any background."""
    V = space.scalar
    n, m = V.n_dofs, len(weights)
    step = max(_assembly.GRAM_ROWS // 7, 1)
    pairs = [(0, 1), (0, 2), (1, 2)]

    def blocks():
        for start in range(0, m, step):
            cells = slice(start, start + step)
            G = grads_of(cells)  # (b, 4, 3)
            w = weights[cells][:, None]
            d = V.element_dofs[cells] if elements is None else V.element_dofs[elements[cells]]
            d = d.astype(index_dtype(3 * n), copy=False)
            s = np.sqrt(2.0 * mu * w)
            yield (np.concatenate([d + i * n for i in range(3)]), np.concatenate([s * G[:, :, i] for i in range(3)]))
            s = np.sqrt(mu * w)
            yield (np.concatenate([np.concatenate([d + i * n, d + j * n], axis=1) for i, j in pairs]),
                   np.concatenate([np.concatenate([s * G[:, :, j], s * G[:, :, i]], axis=1) for i, j in pairs]))
            if lam > 0:
                yield np.concatenate([d + i * n for i in range(3)], axis=1), np.sqrt(lam * w) * G.transpose(0, 2, 1).reshape(len(d), 12)

    return gram_sum(blocks(), 3 * n)


def _traction_rows(G, normals, mu, lam):
    """S (m, 4, 3, 3): S[t, a, l, k] the component l of sigma(phi_a e_k) n on tet t,
    mu delta_kl g_a . n + mu (g_a)_l n_k + lam (g_a)_k n_l (G (m, 4, 3), n (m, 3))."""
    gn = np.einsum("mad,md->ma", G, normals)
    S = mu * np.einsum("mal,mk->malk", G, normals) + lam * np.einsum("mak,ml->malk", G, normals)
    S += mu * gn[..., None, None] * np.eye(3)
    return S


def _elasticity_nitsche_blocks(space, measure, sign, mu, lam, gamma):
    """(the field's cut tets el (m,), element matrices (m, 4, 4, 3, 3)) of the elasticity Nitsche
    terms -(sigma(u) n, v) - (u, sigma(v) n) + ((2 mu + lam) gamma / h)(u, v) over the pieces S_K of
    the cut tets, exact for P1: sigma(u) n is constant on S_K, so with p_b = int_{S_K} phi_b, the
    traction rows S of :func:`_traction_rows` and the piece mass M_K,

        K[(l, b), (k, a)] = -p_b S[a, l, k] - S[b, k, l] p_a + (2 mu + lam) gamma / h_K M_K[b, a] delta_lk,

    n = ``sign`` n_h the outward normal of the field's side."""
    V = space.scalar
    cut = measure.cut
    edges, diagonal, p = _piece_moments(cut)
    es = cut.elements(CUT)
    el = V.local_elements(measure, np.arange(es.n_elements))
    S = _traction_rows(V.gradients_of(el), sign * es.normals, mu, lam)
    M = np.zeros((len(el), 4, 4))
    i, j = TET_EDGES[:, 0], TET_EDGES[:, 1]
    M[:, i, j] = edges
    M[:, j, i] = edges
    M[:, np.arange(4), np.arange(4)] = diagonal
    K = -np.einsum("mb,malk->mbalk", p, S) - np.einsum("mbkl,ma->mbalk", S, p)
    K += ((2.0 * mu + lam) * gamma / es.h)[:, None, None, None, None] * M[..., None, None] * np.eye(3)
    return el, K


def _element_blocks(space, el, blocks, into=None, scale=1.0):
    """sum_K of symmetric element matrices (m, 4, 4, 3, 3) of a vector field on the scalar field's
    elements ``el``: into the 3 x 3 blocks of ``into`` (a :class:`~cutfem.fem.assembly.VectorSum` on
    a structured box, times ``scale``; returns None), or as one COO matrix when ``into`` is None
    (exactly symmetric either way)."""
    V = space.scalar
    dofs = V.element_dofs[el]
    if into is not None:
        into.add_block_elements(dofs, blocks, scale=scale)
        return None
    n = V.n_dofs
    comp = np.arange(3) * n
    rows = np.broadcast_to(dofs[:, :, None, None, None] + comp[None, None, None, :, None], blocks.shape)
    cols = np.broadcast_to(dofs[:, None, :, None, None] + comp[None, None, None, None, :], blocks.shape)
    A = sp.coo_matrix((blocks.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, 3 * n)).tocsr()
    return (0.5 * (A + A.T)).tocsr()
