"""The built-in terms of linear elasticity on a vector field.

-div sigma(u) = f with sigma(u) = 2 mu eps(u) + lam (div u) I, eps(u) = (grad u + grad u^T) / 2:

* :func:`elasticity`, a(u, v) = (2 mu eps(u), eps(v)) + (lam div u, div v) over a volume;
* :func:`elasticity_nitsche`, u = g on Gamma by symmetric Nitsche,
  -(sigma(u) n, v) - (u, sigma(v) n) + ((2 mu + lam) gamma / h) (u, v) over Gamma_h, with its
  right-hand side ``.load``, -(g, sigma(v) n) + ((2 mu + lam) gamma / h) (g, v).

Both act on a :class:`~cutfem.fem.spaces.VectorSpace` and are integrands of the form language like
the terms of :mod:`cutfem.fem.terms` (``form.by_quadrature()`` evaluates their integrands), with
exact P1 implementations (:mod:`cutfem.fem.closed_forms`): on a structured box the element matrices
per Kuhn type (volume) and per cut tet (Nitsche) go into 3 x 3 blocks of the lattice slots, one CSR
pass with the terms that act per component (the ghost penalty, scaled by 2 mu + lam, and the
mass); otherwise a Gram product of the rows of eps and div (volume) and element matrices (Nitsche).
A ghost penalty is ``(2 * mu + lam) * gamma_g * face_jump_penalty(dF, h_power=1)``: that term acts
on each component.
"""

from __future__ import annotations

import numpy as np

from .closed_forms import (_elasticity_gram, _elasticity_nitsche_blocks, _element_blocks, _kuhn_elasticity, _point_load,
                           _traction_rows)
from .forms import Form, _number
from ..geometry.measures import ElementVolume, SideVolume, SurfacePieces
from .pointwise import _require_function, dot, inner
from .spaces import VectorSpace
from .terms import (Nitsche, _integrand, _nitsche_advice, _nitsche_side, _outward_sign, _positive, _require, _same_elements,
                    _times)

__all__ = ["elasticity", "elasticity_nitsche"]


def _vector_field(space, what):
    if not isinstance(space, VectorSpace):
        raise TypeError(f"{what} acts on a vector field, VectorSpace(V); got {space!r}")


def _material(mu, lam):
    """mu > 0 and lam >= 0 as floats, or a ValueError naming the one that is not."""
    _positive(mu=mu)
    lam = _number("lam", lam)
    if lam < 0:
        raise ValueError(f"lam must be a number >= 0 (the Lame parameter lambda), got {lam!r}")
    return float(mu), lam


def _stress(u, w):
    """sigma(u) = 2 mu eps(u) + lam div(u) I of a vector basis function, (m, 1, 3, 3)."""
    return 2.0 * w.mu * u.sym_grad + w.lam * u.div[..., None, None] * np.eye(3)


def _elasticity_exact(term, space, into, scale):
    _vector_field(space, "elasticity")
    measure, mu, lam = term.measure, term.params["mu"], term.params["lam"]
    V = space.scalar
    if _same_elements(V, measure):
        if into is not None and into.lattice:
            return _kuhn_elasticity(space, measure.part_volumes, mu, lam, into, scale)
        return _elasticity_gram(space, V.gradients_of, measure.part_volumes, mu, lam)
    el = V.local_elements(measure, np.arange(measure.elements.n_elements))
    return _elasticity_gram(space, lambda cells: V.gradients_of(el[cells]), measure.part_volumes, mu, lam, el)


_ELASTICITY = _integrand("elasticity", lambda u, v, w: 2.0 * w.mu * inner(u.sym_grad, v.sym_grad) + w.lam * u.div * v.div,
                         symmetric=True, exact=_elasticity_exact)


def elasticity(measure, mu: float, lam: float, field=None) -> Form:
    """(2 mu eps(u), eps(v)) + (lam div u, div v) over a volume measure (a side of the cut or whole
    tets), on a vector field.  mu > 0, lam >= 0.

    Exact for P1: per tet T the gradients G are constant, and for u = phi_a e_k, v = phi_b e_l the
    integrand is mu delta_kl G_a . G_b + mu (G_b)_k (G_a)_l + lam (G_b)_l (G_a)_k, times
    |T ∩ side|.  On a structured box these element matrices are a table per Kuhn type, summed into
    3 x 3 blocks of the lattice slots (:func:`~cutfem.fem.closed_forms._kuhn_elasticity`); otherwise
    the Gram product of the rows of eps and div (:func:`~cutfem.fem.closed_forms._elasticity_gram`).
    Its kernel (no boundary condition) is the rigid motions a + b x x."""
    _require(measure, (SideVolume, ElementVolume), "elasticity")
    mu, lam = _material(mu, lam)
    return _ELASTICITY.on(measure, field, mu=mu, lam=lam)


def _elasticity_nitsche_exact(term, space, into, scale):
    _vector_field(space, "elasticity_nitsche")
    measure, p = term.measure, term.params
    sign = _outward_sign(space, measure, "elasticity_nitsche")
    el, blocks = _elasticity_nitsche_blocks(space, measure, sign, p["mu"], p["lam"], p["gamma"])
    return _element_blocks(space, el, blocks, into if into is not None and into.lattice else None, scale)


def _elasticity_nitsche_matrix(u, v, w):
    n = w.outward * w.n
    return (-inner(dot(_stress(u, w), n), v) - inner(dot(_stress(v, w), n), u)
            + inner((2.0 * w.mu + w.lam) * w.gamma / w.h * u, v))


def _elasticity_nitsche_load_exact(term, space):
    _vector_field(space, "elasticity_nitsche")
    measure, p = term.measure, term.params
    mu, lam, gamma = p["mu"], p["lam"], p["gamma"]
    sign = _outward_sign(space, measure, "elasticity_nitsche")
    V = space.scalar

    def local(quad, el, phi, gw):
        if gw.ndim != 3 or gw.shape[2] != 3:
            raise ValueError(f"elasticity_nitsche: g must return vectors, shape (m, q, 3); got {gw.shape}")
        S = _traction_rows(V.gradients_of(el), sign * quad.normal, mu, lam)
        penalty = ((2.0 * mu + lam) * gamma / measure.h[quad.parent])[:, None, None]
        return penalty * np.einsum("mqb,mql->mbl", phi, gw) - np.einsum("mc,mbcl->mbl", gw.sum(axis=1), S)

    return _point_load(V, measure, term.integrand.degree, p["g"], "elasticity_nitsche: g(x)", local).T.reshape(-1)


_ELASTICITY_NITSCHE = _integrand("elasticity_nitsche", _elasticity_nitsche_matrix, symmetric=True, exact=_elasticity_nitsche_exact,
                                 prepare=_nitsche_side, advice=_nitsche_advice)
_ELASTICITY_NITSCHE_LOAD = _integrand(
    "elasticity_nitsche load",
    lambda v, w: _times(w.at(w.g), (2.0 * w.mu + w.lam) * w.gamma / w.h * v - dot(_stress(v, w), w.outward * w.n)),
    linear=True, exact=_elasticity_nitsche_load_exact, prepare=_nitsche_side)


def elasticity_nitsche(measure: SurfacePieces, mu: float, lam: float, gamma: float = 10.0, g=None, field=None) -> Nitsche:
    """Symmetric Nitsche terms of u = g on Gamma for linear elasticity:

        -(sigma(u) n, v)_Gamma - (u, sigma(v) n)_Gamma + ((2 mu + lam) gamma / h) (u, v)_Gamma,

    n the outward unit normal of the field's side (n_h for ``VectorSpace(CutSpace(cut, NEG))``,
    -n_h for POS) and h the local h_T of the cut tet; with ``g`` (points (m, q, 3) -> (m, q, 3))
    the right-hand side is the returned form's ``.load``, -(g, sigma(v) n) + ((2 mu + lam) gamma /
    h)(g, v), with the same parameters.  gamma must exceed an inverse-estimate constant (the
    form's ``indefinite_hint`` names it, as :func:`~cutfem.fem.terms.nitsche`'s does).

    Exact for P1 (:func:`~cutfem.fem.closed_forms._elasticity_nitsche_blocks`): sigma(u) n is
    constant on each piece, so the element matrices need only the integrals of the basis functions
    over the piece and its mass matrix."""
    _positive(gamma=gamma)
    _require(measure, SurfacePieces, "elasticity_nitsche")
    mu, lam = _material(mu, lam)
    if g is not None:
        _require_function(g, "elasticity_nitsche: g")
    return Nitsche(measure, gamma, g, field, matrix=_ELASTICITY_NITSCHE, rhs=_ELASTICITY_NITSCHE_LOAD,
                   params={"mu": mu, "lam": lam})
