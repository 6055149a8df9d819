"""Domains made of several level sets: Boolean combinations of their insides (docs/math.md §16).

Level sets phi_1..phi_m, each with the inside {phi_k < 0}, combine into a domain Omega by
:func:`intersection`, :func:`union`, :func:`difference` and :func:`complement`, nested freely::

    import cutfem as cf
    ball, cap = cf.Sphere(1.0), cf.Plane((0, 0, 1), (0, 0, 0.5))
    omega = cf.intersection(ball, cap)              # the ball below z = 0.5
    cut = cf.cut_mesh(box, omega)                   # cut.dx(cf.NEG), cut.ds(0) the sphere part, cut.ds(1) the disc

A part is a :class:`Domain` or anything :func:`~cutfem.geometry.cut.cut_mesh` takes as one level
set (a level set, a callable phi(x), an array of nodal values).  The level sets of a domain are its
distinct parts (the same object twice is one level set), numbered 0..m-1 in the order in which
they first appear (:attr:`Domain.levelsets`) and named phi1..phim in text.  Which side of each level
set a point lies on is all that decides whether it is in Omega, so a domain is a Boolean function of
m bits, evaluated once for every sign pattern (:meth:`Domain.table`): that table is what the cut
uses.  The same domains are written as text on the command line (:meth:`Domain.from_text`):
``phi1 & phi2`` (intersection), ``phi1 | phi2`` (union), ``phi1 - phi2`` (difference), ``~phi1``
(complement), with parentheses.
"""

from __future__ import annotations

import ast

import numpy as np

__all__ = ["Domain", "intersection", "union", "difference", "complement", "MAX_LEVELSETS"]

#: the most level sets one domain may combine: the cut evaluates the domain on every sign pattern
#: (2^m of them) and codes the side of each level set in one bit of an integer
MAX_LEVELSETS = 16

_SYMBOL = {"and": " & ", "or": " | "}


class Domain:
    """A Boolean combination of the insides {phi_k < 0} of level sets; made by :func:`intersection`,
    :func:`union`, :func:`difference`, :func:`complement` (see the module docstring).

    ``levelsets``: the distinct level sets, in order of first appearance; ``names``: phi1..phim;
    :meth:`contains` evaluates the domain on sides given per level set, :meth:`table` on every sign
    pattern; :meth:`value` is one level set of Omega (max for an intersection, min for a union,
    minus for a complement), for sampling where Omega lies."""

    def __init__(self, op: str, parts: tuple):
        self.op, self.parts = op, parts
        seen = []
        for leaf in self._leaves():
            if not any(leaf is s for s in seen):
                seen.append(leaf)
        if len(seen) > MAX_LEVELSETS:
            raise ValueError(f"a domain combines at most {MAX_LEVELSETS} level sets, this one {len(seen)}: the cut evaluates it "
                             "on every pattern of their signs; combine fewer level sets, or merge some into one (e.g. a "
                             "box as one level set max(|x| - a, |y| - b, |z| - c))")
        self.levelsets = tuple(seen)

    def _leaves(self):
        if self.op == "leaf":
            yield self.parts[0]
            return
        for p in self.parts:
            yield from p._leaves()

    @property
    def names(self) -> tuple:
        """phi1..phim: the names of the level sets in text (:meth:`from_text`, :meth:`__str__`)."""
        return tuple(f"phi{k + 1}" for k in range(len(self.levelsets)))

    def index(self, levelset) -> int:
        """The number (0..m-1) of a level set of the domain: the object itself, its number, or its
        name phi1..phim; a ValueError naming the level sets otherwise."""
        if isinstance(levelset, str):
            if levelset in self.names:
                return self.names.index(levelset)
        elif isinstance(levelset, (int, np.integer)) and not isinstance(levelset, (bool, np.bool_)):
            if 0 <= levelset < len(self.levelsets):
                return int(levelset)
        else:
            for k, s in enumerate(self.levelsets):
                if s is levelset:
                    return k
        raise ValueError(f"{levelset!r} is not a level set of the domain {self}: give one of its level sets, its number "
                         f"0..{len(self.levelsets) - 1} or its name ({', '.join(self.names)})")

    def contains(self, inside) -> np.ndarray:
        """Whether points are in Omega, from ``inside`` (m, ...) bool: inside[k] says phi_k < 0."""
        inside = np.asarray(inside, dtype=bool)
        if inside.shape[:1] != (len(self.levelsets),):
            raise ValueError(f"contains needs one row of sides per level set ({len(self.levelsets)}), got shape {inside.shape}")
        return self._evaluate(inside, self.levelsets)

    def _evaluate(self, inside, levelsets):
        if self.op == "leaf":
            return inside[_position(levelsets, self.parts[0])]
        values = [p._evaluate(inside, levelsets) for p in self.parts]
        if self.op == "not":
            return ~values[0]
        out = values[0].copy()
        for v in values[1:]:
            out = (out & v) if self.op == "and" else (out | v)
        return out

    def table(self) -> np.ndarray:
        """(2^m,) bool: whether the sign pattern c is in Omega, bit k of c set when phi_k < 0."""
        m = len(self.levelsets)
        codes = np.arange(1 << m, dtype=np.int64)
        return self.contains((codes[None, :] >> np.arange(m)[:, None]) & 1)

    def value(self, x) -> np.ndarray:
        """A level set of Omega at points x (..., 3): max over an intersection, min over a union,
        minus for a complement.  For sampling where Omega lies (its sign is the domain's); the cut
        uses the level sets themselves."""
        if self.op == "leaf":
            leaf = self.parts[0]
            if isinstance(leaf, np.ndarray):
                raise TypeError("a domain of nodal values has no values between the nodes: give its level sets as functions")
            f = leaf.value if hasattr(leaf, "value") else leaf
            return np.asarray(f(x), dtype=float)
        values = [p.value(x) for p in self.parts]
        if self.op == "not":
            return -values[0]
        return np.maximum.reduce(values) if self.op == "and" else np.minimum.reduce(values)

    def bounds(self):
        """A box (lower (3,), upper (3,)) containing Omega, from the bounds of the level sets that
        have one (:meth:`~cutfem.geometry.levelset.LevelSet.bounds`), or None when Omega may be
        unbounded (a complement, a union with an unbounded part, an intersection of half-spaces
        only)."""
        if self.op == "leaf":
            b = getattr(self.parts[0], "bounds", None)
            b = b() if callable(b) else None
            return None if b is None else (np.asarray(b[0], float), np.asarray(b[1], float))
        if self.op == "not":
            return None
        boxes = [p.bounds() for p in self.parts]
        if self.op == "or":
            if any(b is None for b in boxes):
                return None
            return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)
        known = [b for b in boxes if b is not None]
        if not known:
            return None
        return np.max([b[0] for b in known], axis=0), np.min([b[1] for b in known], axis=0)

    def __str__(self) -> str:
        return self._text(self.levelsets)

    def _text(self, levelsets) -> str:
        if self.op == "leaf":
            return f"phi{_position(levelsets, self.parts[0]) + 1}"
        inner = [p._text(levelsets) if p.op in ("leaf", "not") else f"({p._text(levelsets)})" for p in self.parts]
        if self.op == "not":
            return "~" + inner[0]
        return _SYMBOL[self.op].join(inner)

    def __repr__(self) -> str:
        return f"Domain({self}; " + ", ".join(f"{n} = {s!r}" for n, s in zip(self.names, self.levelsets)) + ")"

    @classmethod
    def from_text(cls, text: str, levelsets) -> "Domain":
        """The domain written as ``text`` over the level sets ``levelsets`` (a sequence), named
        phi1..phim in it: ``&`` intersection, ``|`` union, ``-`` difference, ``~`` complement,
        parentheses.  The domain's level sets are ``levelsets`` in the order given (phiK is
        ``levelsets[K - 1]``), each used.  Parsed as a Python expression whose tree is checked:
        anything else (a call, a number, another name) is refused with a ValueError naming what is
        allowed."""
        levelsets = list(levelsets)
        names = {f"phi{k + 1}": s for k, s in enumerate(levelsets)}
        allowed = (f"the names {', '.join(names)}, " if names else "") + "& (intersection), | (union), - (difference), ~ (complement) and parentheses"
        try:
            tree = ast.parse(str(text).strip(), mode="eval").body
        except SyntaxError:
            raise ValueError(f"the domain {text!r} is not an expression of {allowed}") from None

        def build(node):
            if isinstance(node, ast.Name):
                if node.id not in names:
                    raise ValueError(f"the domain {text!r} names {node.id!r}, which is not one of its level sets: use "
                                     f"{', '.join(names) or 'phi1, phi2, ...'} (phiK the K-th level set given)")
                return names[node.id]
            if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.BitAnd, ast.BitOr, ast.Sub)):
                a, b = build(node.left), build(node.right)
                return {ast.BitAnd: intersection, ast.BitOr: union, ast.Sub: difference}[type(node.op)](a, b)
            if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.Invert):
                return complement(build(node.operand))
            raise ValueError(f"the domain {text!r} holds {ast.unparse(node)!r}; a domain is written with {allowed}")

        domain = _domain(build(tree))
        unused = [n for n, s in names.items() if not any(s is t for t in domain.levelsets)]
        if unused or len(domain.levelsets) != len(levelsets):
            raise ValueError(f"the domain {text!r} does not use {', '.join(unused) or 'every level set given'}: give only "
                             "the level sets the domain combines, each once")
        domain.levelsets = tuple(levelsets)  # numbered as given: phiK is the K-th level set of the list
        return domain


def _leaf(levelset) -> Domain:
    if not (isinstance(levelset, np.ndarray) or hasattr(levelset, "value") or callable(levelset)):
        raise TypeError(f"a part of a domain is a Domain or a level set (a LevelSet, a callable phi(x) of points (..., 3), or "
                        f"an array of nodal values), got {type(levelset).__name__}")
    return Domain("leaf", (levelset,))


def _domain(part) -> Domain:
    return part if isinstance(part, Domain) else _leaf(part)


def _position(levelsets, leaf) -> int:
    return next(k for k, s in enumerate(levelsets) if s is leaf)


def _combine(op: str, parts) -> Domain:
    return Domain(op, tuple(_domain(p) for p in parts))


def intersection(*parts) -> Domain:
    """Omega = the intersection of the parts (each a :class:`Domain` or a level set's inside
    {phi < 0}); at least one part."""
    if not parts:
        raise ValueError("intersection needs at least one part")
    return _combine("and", parts)


def union(*parts) -> Domain:
    """Omega = the union of the parts (each a :class:`Domain` or a level set's inside); at least one part."""
    if not parts:
        raise ValueError("union needs at least one part")
    return _combine("or", parts)


def difference(a, b) -> Domain:
    """Omega = a minus b = a ∩ complement(b) (each a :class:`Domain` or a level set's inside)."""
    return _combine("and", (a, complement(b)))


def complement(a) -> Domain:
    """Omega = the complement of a (a :class:`Domain` or a level set's inside): {phi >= 0} for a level set."""
    return _combine("not", (a,))
