"""Compiled kernels of the isoparametric map Theta_h (:mod:`cutfem.geometry.isoparametric`): Theta_h and
D Theta_h at points of the moved tets, and the deformed weights and normals, point by point (the numpy
formulas held several (cells, points, 3, 3) temporaries a block).  Every point is one thread's work,
so the results do not depend on the number of threads."""

from __future__ import annotations

import numpy as np
from numba import prange

from ..jit import parallel_kernel
from .numbering import TET_EDGES

__all__ = ["p2_map", "deformed_measure"]

#: cells a thread takes at once
CHUNK = 256


@parallel_kernel
def p2_map(vertices, grads, shifts, points, theta, jac):
    """Theta_h (m, q, 3) and D Theta_h (m, q, 3, 3) into ``theta`` and ``jac`` at ``points`` (m, q, 3) of
    tets ``vertices`` (m, 4, 3) with barycentric gradients ``grads`` (m, 4, 3) whose P2 nodes have
    ``shifts`` (m, 10, 3): x + lam^T Q lam and I + 2 (Q lam)^T grad lam, Q the quadratic form of each
    component's shifts (Q_ii = v_i, Q_ij = 2 v_ij - (v_i + v_j) / 2, :func:`~cutfem.geometry.isoparametric.quadratic_form`)."""
    m, q = points.shape[0], points.shape[1]
    for ch in prange((m + CHUNK - 1) // CHUNK):
        Q = np.empty((4, 4, 3))
        lam = np.empty(4)
        half = np.empty((4, 3))
        for t in range(ch * CHUNK, min(m, (ch + 1) * CHUNK)):
            v = shifts[t]
            for a in range(4):
                for c in range(3):
                    Q[a, a, c] = v[a, c]
            for e in range(6):
                i, j = TET_EDGES[e, 0], TET_EDGES[e, 1]
                for c in range(3):
                    Q[i, j, c] = Q[j, i, c] = 2.0 * v[4 + e, c] - 0.5 * (v[i, c] + v[j, c])
            g = grads[t]
            for p in range(q):
                x = points[t, p]
                s = 0.0
                for a in range(1, 4):
                    lam[a] = ((x[0] - vertices[t, 0, 0]) * g[a, 0] + (x[1] - vertices[t, 0, 1]) * g[a, 1]
                              + (x[2] - vertices[t, 0, 2]) * g[a, 2])
                    s += lam[a]
                lam[0] = 1.0 - s
                for a in range(4):
                    for c in range(3):
                        half[a, c] = Q[a, 0, c] * lam[0] + Q[a, 1, c] * lam[1] + Q[a, 2, c] * lam[2] + Q[a, 3, c] * lam[3]
                for c in range(3):
                    theta[t, p, c] = x[c] + lam[0] * half[0, c] + lam[1] * half[1, c] + lam[2] * half[2, c] + lam[3] * half[3, c]
                    for d in range(3):
                        jac[t, p, c, d] = 2.0 * (half[0, c] * g[0, d] + half[1, c] * g[1, d] + half[2, c] * g[2, d]
                                                 + half[3, c] * g[3, d]) + (1.0 if c == d else 0.0)


@parallel_kernel
def deformed_measure(jac, normals, det, factor, normal):
    """Per point of the Jacobians ``jac`` (m, q, 3, 3): ``det`` (m, q) det J and, on a surface
    (``normals`` (m, 1 or q, 3) the planar normals n_h; empty for a volume), ``factor`` (m, q)
    |cof(J) n_h| and ``normal`` (m, q, 3) cof(J) n_h / |cof(J) n_h|, with
    cof(J) n = n_0 (c_1 x c_2) + n_1 (c_2 x c_0) + n_2 (c_0 x c_1), c_i the columns of J."""
    m, q = det.shape
    for ch in prange((m + CHUNK - 1) // CHUNK):
        cof = np.empty((3, 3))  # row i: c_{i+1} x c_{i+2}
        for t in range(ch * CHUNK, min(m, (ch + 1) * CHUNK)):
            for p in range(q):
                J = jac[t, p]
                for i in range(3):
                    a, b = (i + 1) % 3, (i + 2) % 3
                    cof[i, 0] = J[1, a] * J[2, b] - J[2, a] * J[1, b]
                    cof[i, 1] = J[2, a] * J[0, b] - J[0, a] * J[2, b]
                    cof[i, 2] = J[0, a] * J[1, b] - J[1, a] * J[0, b]
                det[t, p] = J[0, 0] * cof[0, 0] + J[1, 0] * cof[0, 1] + J[2, 0] * cof[0, 2]
                if normals.shape[0] > 0:
                    n = normals[t, p if normals.shape[1] > 1 else 0]
                    s0 = n[0] * cof[0, 0] + n[1] * cof[1, 0] + n[2] * cof[2, 0]
                    s1 = n[0] * cof[0, 1] + n[1] * cof[1, 1] + n[2] * cof[2, 1]
                    s2 = n[0] * cof[0, 2] + n[1] * cof[1, 2] + n[2] * cof[2, 2]
                    f = np.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
                    factor[t, p] = f
                    normal[t, p, 0], normal[t, p, 1], normal[t, p, 2] = s0 / f, s1 / f, s2 / f
