"""Moving domains, Eulerian (Lehrenfeld and Olshanskii, ESAIM: M2AN 53, 2019): the pieces of a time
step on a fixed background mesh.

At time t_{n+1} the domain is Omega^{n+1} = {phi(., t_{n+1}) < 0}.  A BDF step needs the previous
solutions on Omega^{n+1}, but they were computed on the earlier domains.  So each solution lives on
an *extended* domain: the tets of {phi < delta} (:class:`ActiveDomain`, ``space``), delta a strip
width larger than the distance the boundary moves in the steps a BDF formula looks back
(:func:`strip_width`: delta = c order w dt, w the largest normal speed).  The forms integrate over
Omega^{n+1} (``dx``, ``ds``), and a ghost penalty on the facets of the strip (``dF``: the interior
facets of the extended tets with a tet not strictly inside {phi < -delta}) extends the solution
smoothly past the boundary; it also makes the matrix uniformly well conditioned, as the ghost
penalty of a fixed domain does.  The previous solutions move to the new space by their values at
the background nodes (:func:`transfer`): every node of a tet that meets Omega^{n+1} was active in
the earlier extended domain when delta covers the motion, which :func:`transfer` checks.
"""

from __future__ import annotations

import numpy as np

from ..geometry.cut import cut_mesh
from ..geometry.levelset import LevelSet
from ..geometry.markers import NEG
from .spaces import CutSpace

__all__ = ["Shifted", "ActiveDomain", "strip_width", "transfer"]


class Shifted(LevelSet):
    """The level set phi - delta, whose negative side is {phi < delta}: for a signed distance the
    domain grown by the width delta (a larger sphere for a sphere)."""

    def __init__(self, levelset: LevelSet, delta: float):
        delta = float(delta)
        if not np.isfinite(delta):
            raise ValueError(f"Shifted: delta must be a finite number, got {delta!r}")
        self.base, self.delta = levelset, delta
        self.lipschitz = levelset.lipschitz
        self.is_distance = levelset.is_distance
        self.area = self.volume = None

    def __repr__(self) -> str:
        return f"Shifted({self.base!r}, {self.delta!r})"

    def value(self, x):
        return self.base.value(x) - self.delta

    def gradient(self, x):
        return self.base.gradient(x)

    def hessian(self, x):
        return self.base.hessian(x)

    def bounds(self):
        """The base's box grown by delta (a distance moves its zero set by delta), or None."""
        bounds = getattr(self.base, "bounds", None)
        box = bounds() if callable(bounds) else None
        if box is None or not self.is_distance:
            return None
        lower, upper = (np.asarray(b, dtype=float) for b in box)
        grow = max(self.delta, 0.0)
        return lower - grow, upper + grow


def strip_width(speed: float, dt: float, order: int = 1, factor: float = 1.5) -> float:
    """delta = factor * order * speed * dt: the boundary moves at most speed * dt in a step, and a
    BDF formula of ``order`` looks ``order`` steps back; ``factor`` > 1 is the margin."""
    for name, value in (("speed", speed), ("dt", dt), ("factor", factor)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"strip_width: {name} must be a positive finite number, got {value!r}")
    if order not in (1, 2):
        raise ValueError(f"strip_width: order is 1 or 2 (the BDF formulas), got {order!r}")
    return factor * order * speed * dt


class ActiveDomain:
    """The domain {phi < 0} of one time and its extension {phi < delta} on a fixed background.

    ``cut``: the cut of phi (its ``dx(NEG)`` and ``ds()`` are the forms' measures); ``extended``: the
    cut of phi - delta; ``space``: the P1 field on the extended tets; ``strip_facets``: the interior
    facets of the extended tets with a tet in the strip (a node with phi > -delta); ``dx``, ``ds``,
    ``dF`` the measures over Omega, Gamma and the strip facets."""

    def __init__(self, background, levelset: LevelSet, delta: float):
        delta = float(delta)
        if not (np.isfinite(delta) and delta > 0):
            raise ValueError(f"ActiveDomain: the strip width delta must be a positive finite number, got {delta!r}; "
                             "take strip_width(speed, dt, order)")
        self.delta = delta
        self.cut = cut_mesh(background, levelset)
        self.extended = cut_mesh(background, Shifted(levelset, delta))
        self.space = CutSpace(self.extended, NEG)
        es = self.space.elements
        in_strip = es.levelset_values[es.tets].max(axis=1) > -2.0 * delta  # phi - delta > -2 delta: phi > -delta
        facets = self.extended.interior_facets(NEG)
        pairs = facets.pairs
        self.strip_facets = facets.subset(in_strip[pairs[:, 0]] | in_strip[pairs[:, 1]])
        self.dx = self.cut.dx(NEG)
        self.ds = self.cut.ds()
        self.dF = self.extended.dF(self.strip_facets)

    def __repr__(self) -> str:
        return f"ActiveDomain(delta={self.delta:g}, dofs={self.space.n_dofs}, strip facets={self.strip_facets.n_facets})"


def transfer(u, old, new, over=None) -> np.ndarray:
    """The coefficients of ``u`` (a field of the space ``old``) on the space ``new`` of the same
    background: its values at the shared background nodes, zero at the new nodes.  ``over``: a
    measure (the new domain's ``dx``) whose cells must have every node in ``old``, else a ValueError
    naming the fix (a wider strip): there the zero values would enter the forms."""
    u = np.asarray(u, dtype=float)
    if u.shape[0] != old.n_dofs:
        raise ValueError(f"transfer: u has {u.shape[0]} values, the old space {old.n_dofs} unknowns")
    old_ids, new_ids = np.asarray(old.node_ids), np.asarray(new.node_ids)
    pos = np.minimum(np.searchsorted(old_ids, new_ids), len(old_ids) - 1)
    found = old_ids[pos] == new_ids
    out = np.zeros((new.n_dofs,) + u.shape[1:])
    out[found] = u[pos[found]]
    if over is not None:
        parent = new.local_elements(over)
        missing = ~found[new.element_dofs[np.unique(parent)]]
        if np.any(missing):
            raise ValueError(f"transfer: {int(missing.any(axis=1).sum())} tets of the new domain have nodes that the old "
                             "field did not have: the boundary moved farther than the strip is wide; widen it (a larger "
                             "factor or order in strip_width) or take smaller steps")
    return out
