"""The P2 Lagrange element on tetrahedra: its dof numbering on an element set, and its basis from barycentric coordinates.

A P2 field on an element set (m tets on p nodes) has the p nodes as its first dofs, numbered as
the P1 field's (so that P1 is a prefix of P2), then the E edges of the set, ordered by their pair
of background node ids: dof p + e is the midpoint of edge e.  On a tet with barycentric
coordinates lambda_0..lambda_3 (gradients G_i, constant) the local basis is, vertices first and
then the edges in :data:`~cutfem.geometry.numbering.TET_EDGES` order,

    vertex i:     phi_i  = lambda_i (2 lambda_i - 1),  grad = (4 lambda_i - 1) G_i,          Hessian 4 G_i G_i^T,
    edge (i, j):  phi_ij = 4 lambda_i lambda_j,        grad = 4 (lambda_j G_i + lambda_i G_j),  Hessian 4 (G_i G_j^T + G_j G_i^T),

each 1 at its own node and 0 at the nine others (docs/math.md §18).  Everything here is one numpy
expression over all cells and points at once.
"""

from __future__ import annotations

import numpy as np

from ..geometry.numbering import TET_EDGES
from .p2_kernels import inverse_3x3

__all__ = ["edge_numbering", "p2_values", "p2_gradients", "p2_hessians", "map_gradients", "map_hessians"]

_I, _J = TET_EDGES[:, 0], TET_EDGES[:, 1]


def edge_numbering(tets: np.ndarray, n_nodes: int):
    """(edges (E, 2), element_edges (m, 6)) of tets (m, 4) on nodes 0..n_nodes-1 numbered in the
    order of the background ids: the unique edges as sorted node pairs in lexicographic order (the
    order of their background node pairs, since the local numbers increase with the background
    ids), and the number of each tet's local edges (:data:`TET_EDGES`)."""
    tets = np.asarray(tets, dtype=np.int64)
    a, b = tets[:, _I], tets[:, _J]
    keys = np.minimum(a, b) * n_nodes + np.maximum(a, b)  # (m, 6)
    unique, inverse = np.unique(keys, return_inverse=True)
    edges = np.stack([unique // n_nodes, unique % n_nodes], axis=1)
    return edges, inverse.reshape(keys.shape)


def p2_values(lam: np.ndarray, whole: int = 0) -> np.ndarray:
    """(..., 10) P2 basis values from barycentric coordinates (..., 4); the first ``whole`` cells
    (of lam (m, q, 4)) share the coordinates of the first, one table for them."""
    if whole > 0:
        out = np.empty(lam.shape[:-1] + (10,))
        out[:whole] = p2_values(lam[0])
        out[whole:] = p2_values(lam[whole:])
        return out
    return np.concatenate([lam * (2.0 * lam - 1.0), 4.0 * lam[..., _I] * lam[..., _J]], axis=-1)


def _lambda_derivatives(lam: np.ndarray) -> np.ndarray:
    """(..., 10, 4) D = d phi / d lambda of the P2 basis at barycentric coordinates (..., 4)."""
    D = np.zeros(lam.shape[:-1] + (10, 4))
    vertices = np.arange(4)
    D[..., vertices, vertices] = 4.0 * lam - 1.0  # (4 lambda_i - 1) G_i
    edges = np.arange(4, 10)
    D[..., edges, _I] = 4.0 * lam[..., _J]  # 4 lambda_j G_i + 4 lambda_i G_j
    D[..., edges, _J] = 4.0 * lam[..., _I]
    return D


def p2_gradients(lam: np.ndarray, G: np.ndarray, whole: int = 0) -> np.ndarray:
    """(m, q, 10, 3) P2 basis gradients from barycentric coordinates ``lam`` (m, q, 4) and their
    constant gradients ``G`` (m, 4, 3): D(lam) G with D = d phi / d lambda (10 x 4 per point,
    :func:`_lambda_derivatives`), whose table is made once for the first ``whole`` cells (all of
    them when ``lam`` is a broadcast view): the whole cells share one rule's coordinates, only G differs."""
    m = lam.shape[0]
    whole = m if lam.strides[0] == 0 else whole
    out = np.empty(lam.shape[:2] + (10, 3))
    if whole > 0:
        np.matmul(_lambda_derivatives(lam[:1]), G[:whole, None], out=out[:whole])
    if whole < m:
        np.matmul(_lambda_derivatives(lam[whole:]), G[whole:, None], out=out[whole:])
    return out


def p2_hessians(G: np.ndarray) -> np.ndarray:
    """(m, 1, 10, 3, 3) P2 basis Hessians (constant on each tet) from the barycentric gradients G (m, 4, 3)."""
    vertex = 4.0 * np.einsum("mki,mkj->mkij", G, G)
    cross = np.einsum("mki,mkj->mkij", G[:, _I], G[:, _J])
    edge = 4.0 * (cross + np.swapaxes(cross, -1, -2))
    return np.concatenate([vertex, edge], axis=1)[:, None]


def map_gradients(grads: np.ndarray, jacobians: np.ndarray) -> np.ndarray:
    """Gradients (m, q or 1, k, 3) in the undeformed element mapped to the deformed one:
    D Theta^-T grad^ at each point, with ``jacobians`` D Theta (m, q, 3, 3) -> (m, q, k, 3)."""
    inverse = inverse_3x3(jacobians)  # (m, q, 3, 3); the rows g^T J^-1 of the gradients
    return np.matmul(np.broadcast_to(grads, inverse.shape[:2] + grads.shape[2:]), inverse)


def map_hessians(hessians: np.ndarray, jacobians: np.ndarray, gradients=None, theta_hessians=None) -> np.ndarray:
    """Hessians (m, q or 1, k, 3, 3) in the undeformed element mapped to the deformed one,
    -> (m, q, k, 3, 3): from phi^ = phi o Theta, H^ = J^T H J + sum_c (grad phi)_c H(Theta_c), so

        H = J^-T (H^ - sum_c (grad phi)_c H(Theta_c)) J^-1,

    J = D Theta (m, q, 3, 3), ``gradients`` the mapped gradients grad phi (m, q, k, 3) and
    ``theta_hessians`` H(Theta_c) (m, 3, 3, 3) (None: an affine Theta, no such term)."""
    if theta_hessians is not None:
        hessians = hessians - np.einsum("mqkc,mcij->mqkij", gradients, theta_hessians)
    inverse = inverse_3x3(jacobians)[:, :, None]  # (m, q, 1, 3, 3)
    return np.matmul(np.matmul(np.swapaxes(inverse, -1, -2), hessians), inverse)
