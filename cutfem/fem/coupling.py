"""Built-in terms that couple two fields of a product space: the divergence coupling of Stokes and
the mean-value constraint of a field by a multiplier.

:func:`divergence` is b(u, q) + b(v, p) with b(u, q) = -(div u, q) over a volume, the off-diagonal
blocks of the Stokes saddle-point matrix [[A, B^T], [B, -C]] (docs/math.md §14).  For P1 fields div u
is constant on each tet T, so with I_T,j = int_{T ∩ Omega} phi_j (the basis integrals of the pressure
on the cell's part) and G_T the velocity basis gradients,

    B[j, (c, a)] = -sum_T I_T,j (G_T)_{a,c},

the product E_I^T E_G of two sparse cell-by-dof matrices (one row per cell or sub-tet of the
measure): no element loop, no basis-pair evaluation, exactly the matrix that quadrature of the
integrand gives (tested against ``form.by_quadrature()``).  :func:`mean_constraint` is (p, mu) +
(q, lam) with lam a :class:`~cutfem.fem.spaces.RealSpace` field: the basis integrals of p as a row
and a column.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .forms import Form, Integrand, Term, _field_index
from ..geometry.measures import ElementVolume, FacetMeasure, SideVolume
from .pointwise import dot
from .spaces import ProductSpace, RealSpace, VectorSpace
from .terms import basis_integrals

__all__ = ["divergence", "mean_constraint"]


def _positions(space, term):
    """The positions of the velocity (a vector field) and the pressure (a scalar field) in ``space``."""
    velocity, pressure = term.params["velocity"], term.params["pressure"]
    if not isinstance(space, ProductSpace):
        raise TypeError(f"divergence couples a velocity and a pressure: assemble it on ProductSpace(u=VectorSpace(V), p=V, ...), "
                        f"not on {space!r}")
    iu, ip = _field_index(space, velocity), _field_index(space, pressure)
    if not isinstance(space.fields[iu], VectorSpace):
        raise TypeError(f"divergence: the velocity field {velocity!r} must be a VectorSpace, got {space.fields[iu]!r}")
    if isinstance(space.fields[ip], VectorSpace) or not hasattr(space.fields[ip], "element_dofs"):
        raise TypeError(f"divergence: the pressure field {pressure!r} must be a scalar finite element field, got {space.fields[ip]!r}")
    return iu, ip


def _prepare(space, term):
    """The names given for the fields replaced by their positions, as the integrand reads them."""
    iu, ip = _positions(space, term)
    return {"velocity": iu, "pressure": ip}


def _cell_rows(dofs, values, n):
    """The CSR matrix (m, n) whose row i holds ``values[i]`` at the columns ``dofs[i]`` (m, k)."""
    m, k = dofs.shape
    return sp.csr_matrix((values.reshape(-1), dofs.reshape(-1), np.arange(0, m * k + 1, k)), shape=(m, n))


def _divergence_exact(term, space):
    iu, ip = _positions(space, term)
    U, P, measure = space.fields[iu].scalar, space.fields[ip], term.measure
    nu, n_p = U.n_dofs, P.n_dofs
    X = sp.csr_matrix((n_p, 3 * nu))  # the (pressure, velocity) block of the term
    for _, quad in measure.blocks(1):
        el_p = P.local_elements(measure, quad.parent)
        el_u = U.local_elements(measure, quad.parent)
        dofs_u, dofs_p = U.element_dofs[el_u], P.element_dofs[el_p]
        if term.params["by_parts"]:  # (v, grad q): the velocity's basis integrals, the pressure's gradients
            E_I = _cell_rows(dofs_u, np.einsum("mqk,mq->mk", U.basis_on(measure, quad, el_u), quad.weights), nu)
            G = P.gradients_of(el_p)
            X = X + sp.hstack([_cell_rows(dofs_p, G[:, :, c].copy(), n_p).T @ E_I for c in range(3)], format="csr")
        else:  # -(div v, q): the pressure's basis integrals, the velocity's gradients
            E_I = _cell_rows(dofs_p, np.einsum("mqk,mq->mk", P.basis_on(measure, quad, el_p), quad.weights), n_p)
            G = U.gradients_of(el_u)  # (m, 4, 3)
            dofs_v = np.concatenate([dofs_u + c * nu for c in range(3)], axis=1)  # component after component
            X = X - E_I.T @ _cell_rows(dofs_v, G.transpose(0, 2, 1).copy(), 3 * nu)
    return _symmetric_pair(space, ip, iu, X)


def _symmetric_pair(space, i, j, B):
    """The (n, n) matrix of ``space`` with the block ``B`` at rows of field i and columns of field j,
    and its transpose at (j, i)."""
    offsets, n = space.offsets, space.n_dofs
    B = sp.csr_matrix(B)
    rows = sp.hstack([sp.csr_matrix((B.shape[0], offsets[j])), B, sp.csr_matrix((B.shape[0], n - offsets[j] - B.shape[1]))],
                     format="csr")
    place = sp.vstack([sp.csr_matrix((offsets[i], n)), rows, sp.csr_matrix((n - offsets[i] - B.shape[0], n))], format="csr")
    return (place + place.T).tocsr()


def _divergence_integrand(u, v, w):
    iu, ip = w.velocity, w.pressure
    if w.by_parts:
        return dot(v[iu], u[ip].grad) + dot(u[iu], v[ip].grad)
    return -(v[iu].div * u[ip] + u[iu].div * v[ip])


_DIVERGENCE = Integrand(_divergence_integrand, False, symmetric=True, degree=1, exact=_divergence_exact, prepare=_prepare,
                        couples=True)
_DIVERGENCE.__name__ = "divergence"


def divergence(measure, velocity="u", pressure="p", by_parts: bool = False) -> Form:
    """-(div u, q) - (div v, p) over a volume measure (a side of the cut or whole tets), on a product
    space with a vector field ``velocity`` and a scalar field ``pressure`` (names or positions):
    the symmetric off-diagonal blocks of Stokes, exact for P1 (the module's formula).

    ``by_parts=True``: (u, grad q) + (v, grad p) instead, which is -(div v, p) + (v . n, p) over the
    boundary of the measure's domain (the divergence theorem, exact for P1 on the polyhedral
    Omega_h): with Nitsche on Gamma_h the two coupling terms of Stokes in one volume term, when
    Omega_h touches no face of the box (as ``cut_mesh`` checks by default).  Its exact path swaps
    the roles: the velocity's basis integrals times the pressure's gradients."""
    if not isinstance(measure, (SideVolume, ElementVolume)):
        raise TypeError(f"divergence integrates over a volume (cut.dx(side) or whole tets), got {measure!r}")
    return Form([(1.0, Term(_DIVERGENCE, measure, None, {"velocity": velocity, "pressure": pressure, "by_parts": bool(by_parts)}))],
                False)


def _mean_positions(space, term):
    if not isinstance(space, ProductSpace):
        raise TypeError(f"mean_constraint couples a field and a multiplier: assemble it on a ProductSpace, not on {space!r}")
    k, m = _field_index(space, term.params["field"]), _field_index(space, term.params["multiplier"])
    if not isinstance(space.fields[m], RealSpace):
        raise TypeError(f"mean_constraint: the multiplier {term.params['multiplier']!r} must be a RealSpace (one constant), "
                        f"got {space.fields[m]!r}")
    if isinstance(space.fields[k], (RealSpace, VectorSpace)):
        raise TypeError(f"mean_constraint: the field {term.params['field']!r} must be a scalar finite element field, "
                        f"got {space.fields[k]!r}")
    return k, m


def _mean_exact(term, space):
    k, m = _mean_positions(space, term)
    column = np.asarray(basis_integrals(term.measure).assemble(space.fields[k]), dtype=float)[:, None]
    return _symmetric_pair(space, k, m, column)


def _mean_prepare(space, term):
    k, m = _mean_positions(space, term)
    return {"field": k, "multiplier": m}


def _mean_integrand(u, v, w):
    return u[w.field] * v[w.multiplier] + v[w.field] * u[w.multiplier]


_MEAN = Integrand(_mean_integrand, False, symmetric=True, degree=1, exact=_mean_exact, prepare=_mean_prepare, couples=True)
_MEAN.__name__ = "mean_constraint"


def mean_constraint(measure, field="p", multiplier="mean") -> Form:
    """(p, mu) + (q, lam) over ``measure``: the mean of the scalar field ``field`` held by the
    multiplier ``multiplier`` (a :class:`~cutfem.fem.spaces.RealSpace`), names or positions in a
    product space.  With the right-hand side 0 the discrete p has mean zero over the measure; the
    block is the field's basis integrals (:func:`~cutfem.fem.terms.basis_integrals`)."""
    if isinstance(measure, FacetMeasure):
        raise TypeError("mean_constraint integrates over cells (a volume or a surface), not over facets")
    return Form([(1.0, Term(_MEAN, measure, None, {"field": field, "multiplier": multiplier}))], False)
