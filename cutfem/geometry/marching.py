"""The case tables of marching tetrahedra: the piece of a plane in a tet from the signs of its nodes.

A P1 level set is linear on a tet T, so its zero set in T is a plane piece whose polygon is fixed by
the sign code of the nodes (bit k set when node k is inside, phi_k < 0): a triangle when one node is
alone on its side, a quadrilateral when the nodes split two and two.  Its vertices are the points
on the edges (i, j) that change sign, listed here in cyclic order, with the orientation of that
order about grad phi (:data:`FLIP`).  The cut of one level set (:mod:`cutfem.geometry.cut`) and the
cut by several (:mod:`cutfem.geometry.csg_cut`) both start from these tables.
"""

from __future__ import annotations

import numpy as np

__all__ = ["CASES", "EDGE_I", "EDGE_J", "NVERT", "FLIP", "TRIANGLE_SLOTS"]


# For each sign pattern (bit k set when node k is inside, phi_k < 0) the polygon of the piece as a
# cyclic list of tet edges (i, j) with i inside, j outside; quads have 4 edges, triangles 3.
def _case_table():
    table = {}
    for mask in range(1, 15):
        inside = [k for k in range(4) if mask >> k & 1]
        outside = [k for k in range(4) if not mask >> k & 1]
        if len(inside) == 1:
            i = inside[0]
            edges = [(i, o) for o in outside]
        elif len(inside) == 3:
            o = outside[0]
            edges = [(i, o) for i in inside]
        else:
            a, b = inside
            c, d = outside
            edges = [(a, c), (a, d), (b, d), (b, c)]
        table[mask] = edges
    return table


CASES = _case_table()


def _case_arrays():
    """Lookup tables indexed by the sign code: edge endpoints (16, 4) and polygon size (16,).
    Triangles repeat their last edge in the fourth slot.  The local node numbers are int8: the
    (m, 4) slot arrays gathered from them are then 8 times smaller than in int64."""
    ei = np.zeros((16, 4), dtype=np.int8)
    ej = np.zeros((16, 4), dtype=np.int8)
    nv = np.zeros(16, dtype=np.int8)
    for code, edges in CASES.items():
        e = np.array(edges + edges[-1:] * (4 - len(edges)))
        ei[code], ej[code], nv[code] = e[:, 0], e[:, 1], len(edges)
    return ei, ej, nv


EDGE_I, EDGE_J, NVERT = _case_arrays()


def _flip_table():
    """(16,) bool: whether the triangles (0, 1, 2) and (0, 2, 3) of the piece, in the polygon order
    of the case table, turn clockwise about grad phi_h in a positively oriented tet.

    The orientation of the piece's polygon relative to grad phi_h cannot change while the nodal
    values keep their signs (the polygon never degenerates), so it is fixed by the sign code; it is
    read off once on the reference tet with values -1 (inside) and +1 (outside).  In a negatively
    oriented tet it is the opposite."""
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    flip = np.zeros(16, dtype=bool)
    for code, edges in CASES.items():
        phi = np.where([code >> k & 1 for k in range(4)], -1.0, 1.0)
        p = np.array([x[i] + phi[i] / (phi[i] - phi[j]) * (x[j] - x[i]) for i, j in edges])
        grad = np.linalg.solve(np.c_[x, np.ones(4)], phi)[:3]
        flip[code] = np.dot(np.cross(p[1] - p[0], p[2] - p[0]), grad) < 0
    return flip


FLIP = _flip_table()


# the polygon slots of the triangles (0, 1, 2) and (0, 2, 3) of a piece, and the same turned over
TRIANGLE_SLOTS = np.array([[0, 1, 2, 0, 2, 3], [0, 2, 1, 0, 3, 2]], dtype=np.int64)
