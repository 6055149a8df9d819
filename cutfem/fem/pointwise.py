"""What an integrand sees at the quadrature points: basis functions, their traces and the quadrature data.

An integrand (:mod:`cutfem.fem.forms`) is called on arrays shaped (cells x quadrature points): the
basis functions ``u`` and ``v`` (:class:`BasisField`: ``value`` (m, q), ``grad`` and ``tgrad``
(m, 1, 3)), on a facet their two traces (:class:`FacetField`, with :func:`jump` and :func:`avg`),
on a product space a tuple with one entry per field, all :data:`ZERO` but one, and ``w``
(:class:`QuadData`): the points, the measure's normal, the local size, ``w.at(f)`` and the term's
parameters.  This module makes those values from a space, a measure and its quadrature, and
checks what a user function returns at the points.
"""

from __future__ import annotations

import numbers

import numpy as np

from ..geometry.measures import Measure

__all__ = ["ZERO", "BasisField", "FacetField", "QuadData", "dot", "jump", "avg"]


def _is_number_zero(other) -> bool:
    """Whether ``other`` is the number 0 (a Python or numpy scalar, or a 0-d array), as ``sum()``
    starts from."""
    return isinstance(other, (numbers.Number, np.ndarray)) and np.ndim(other) == 0 and other == 0


class _Zero:
    """The zero function: what a field that is not being varied contributes to an integrand.
    Absorbs products, vanishes from sums; every attribute (grad, minus, ...) is zero too.  A sum
    of ZERO terms is ZERO, also from ``sum()``, which starts from the number 0 (``0 + ZERO`` is
    ZERO, not 0): the integrand then says it does not couple those fields."""

    __array_ufunc__ = None  # ndarray op ZERO defers to the reflected operators below

    def __repr__(self):
        return "ZERO"

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return self

    def __getitem__(self, key):
        return self

    def __mul__(self, other):
        return self

    __rmul__ = __truediv__ = __mul__

    def __add__(self, other):
        return self if _is_number_zero(other) else other

    __radd__ = __add__

    def __sub__(self, other):
        return self if _is_number_zero(other) else -other

    def __rsub__(self, other):
        return self if _is_number_zero(other) else other

    def __neg__(self):
        return self

    def __pow__(self, power):
        return self


ZERO = _Zero()


class _Probe(_Zero):
    """Stands for a nonzero basis function while the assembly finds which field pairs a form couples."""

    def __repr__(self):
        return "PROBE"

    def __add__(self, other):
        return self

    __radd__ = __sub__ = __rsub__ = __add__

    def __mul__(self, other):
        return ZERO if other is ZERO else self

    __rmul__ = __truediv__ = __mul__


_PROBE = _Probe()


class BasisField:
    """A basis function at quadrature points: ``value`` (m, q), ``grad``, ``tgrad`` (m, 1, 3);
    arithmetic acts on ``value``."""

    __slots__ = ("value", "grad", "tgrad")

    def __init__(self, value, grad, tgrad):
        self.value, self.grad, self.tgrad = value, grad, tgrad

    def __array__(self, dtype=None, copy=None):
        return np.asarray(self.value, dtype=dtype)

    def __mul__(self, other):
        return self.value * (other.value if isinstance(other, BasisField) else other)

    __rmul__ = __mul__

    def __add__(self, other):
        return self.value + (other.value if isinstance(other, BasisField) else other)

    __radd__ = __add__

    def __sub__(self, other):
        return self.value - (other.value if isinstance(other, BasisField) else other)

    def __rsub__(self, other):
        return other - self.value

    def __truediv__(self, other):
        return self.value / (other.value if isinstance(other, BasisField) else other)

    def __rtruediv__(self, other):
        return other / self.value

    def __pow__(self, power):
        return self.value**power

    def __neg__(self):
        return -self.value


class _Traces:
    """A quantity with a value from each side of a facet: ``minus``, ``plus``."""

    __slots__ = ("minus", "plus")

    def __init__(self, minus, plus):
        self.minus, self.plus = minus, plus

    def _two_sided(self, *args):
        raise TypeError("on a facet a basis function has two traces: take jump(u), avg(u) (or of u.grad), or one side, "
                        "u.minus or u.plus, before any arithmetic")

    __add__ = __radd__ = __sub__ = __rsub__ = __mul__ = __rmul__ = __truediv__ = __rtruediv__ = __matmul__ = __rmatmul__ = _two_sided
    __neg__ = __pow__ = _two_sided
    __array_ufunc__ = None  # numpy hands the operation back, and it is refused above


class FacetField(_Traces):
    """A basis function on a facet: its two traces ``minus`` and ``plus`` (:class:`BasisField` or
    :data:`ZERO`); ``value``, ``grad`` give both traces, for :func:`jump` and :func:`avg`."""

    __slots__ = ()

    @property
    def value(self):
        return _Traces(self.minus.value, self.plus.value)

    @property
    def grad(self):
        return _Traces(self.minus.grad, self.plus.grad)


def _value(a):
    return a.value if isinstance(a, BasisField) else a


def jump(a):
    """[a] = a^- - a^+ of a facet quantity (``u``, ``u.grad``, ``u.value``)."""
    if isinstance(a, _Zero):
        return a
    return _value(a.minus) - _value(a.plus)


def avg(a):
    """{a} = (a^- + a^+) / 2 of a facet quantity."""
    if isinstance(a, _Zero):
        return a
    return 0.5 * (_value(a.minus) + _value(a.plus))


def dot(a, b):
    """Dot product over the last axis (zero-aware)."""
    if isinstance(a, _Zero) or isinstance(b, _Zero):
        return ZERO if (a is ZERO or b is ZERO) else _PROBE
    return np.einsum("...d,...d->...", a, b)


def _require_function(f, what: str) -> None:
    if not callable(f):
        raise TypeError(f"{what} must be a function of the points x (m, q, 3), got {type(f).__name__} {f!r}")


def _point_values(f, points: np.ndarray, what: str) -> np.ndarray:
    """``f(points)`` for points (m, q, 3), checked: real, finite values of shape (m, q) or (m, q, c),
    as floats; otherwise an error naming ``what``, the expected and the actual shape (a constant
    is written ``np.full(x.shape[:-1], c)``)."""
    value = np.asarray(f(points))
    if value.dtype.kind == "c":
        raise TypeError(f"{what} returned complex values; only real values are supported")
    if value.dtype.kind not in "biuf":
        raise TypeError(f"{what} must return real numbers, got {value.dtype} values")
    if value.ndim not in (2, 3) or value.shape[:2] != points.shape[:2]:
        raise ValueError(f"{what} must return shape (m, q) or (m, q, c) for points {points.shape}; got {value.shape} "
                         "(a constant c is np.full(x.shape[:-1], c))")
    value = value.astype(float, copy=False)
    finite = np.isfinite(value)
    if not finite.all():
        bad = np.argwhere(~finite)[0]
        raise ValueError(f"{what} is not finite at {np.count_nonzero(~finite)} of its values, e.g. {value[tuple(bad)]} at "
                         f"x = {points[bad[0], bad[1]]}")
    return value


class QuadData:
    """What an integrand sees besides the basis functions: ``x`` (m, q, 3), ``n`` (m, 1, 3) or None,
    ``h`` (m, 1) local sizes, ``parent`` (m,) the measure's element (or facet) of each cell, ``at(f)``
    and the parameters as attributes: the term's own (``own``, given where the term is made) before
    the form-wide ones (``params``, the keywords of :func:`~cutfem.fem.forms.assemble`)."""

    def __init__(self, x, n, h, parent, params, own=None):
        self.x, self.n, self.parent = x, n, parent
        self._h = h  # the local sizes, or a function giving them: computed only when an integrand asks
        self._params = params
        self._own = {} if own is None else own
        self._values = {}  # id(f) -> (f, values): f kept alive, so that its id is not reused
        self._latest = {}  # code object -> the latest function of that code given to at()

    @property
    def params(self):
        """The parameters, the term's own over the form-wide ones (a dict; taken whole, all count as read)."""
        for p in (self._params, self._own):
            if isinstance(p, _Params):
                p.read.update(p)
        return {**self._params, **self._own}

    @property
    def h(self):
        if callable(self._h):
            self._h = self._h()
        return self._h

    def __getattr__(self, name):
        for params in (self.__dict__.get("_own", {}), self.__dict__.get("_params", {})):
            if name in params:
                if isinstance(params, _Params):
                    params.read.add(name)
                return params[name]
        raise AttributeError(f"quadrature data has no field {name!r}; pass it as a keyword to assemble()")

    def at(self, f):
        """``f(x)`` at the quadrature points (m, q) or (m, q, c), evaluated once per block of cells
        for each function object.  The cache holds ``f`` itself beside its values: an id alone is
        reused by CPython once its object is freed, and a function written inline in the integrand
        (``w.at(lambda x: ...)``, a new object at every call) would then get the values of the one
        freed before it.  Such a function is evaluated at every call instead, and only the latest
        object of each code is kept (an inline lambda made again for every basis pair would
        otherwise hold one array of values per pair)."""
        entry = self._values.get(id(f))
        if entry is None or entry[0] is not f:
            code = getattr(f, "__code__", None)
            if code is not None:
                older = self._latest.get(code)
                if older is not None:
                    self._values.pop(id(older), None)
                self._latest[code] = f
            entry = self._values[id(f)] = (f, _point_values(f, self.x, "a function of the points given to w.at"))
        return entry[1]


class _Params(dict):
    """Parameters of one :func:`~cutfem.fem.forms.assemble` call (the form-wide keywords, or one
    term's own), with the names the integrands read (``read``) and whether any integrand was
    evaluated (``evaluated``: a measure with no cells evaluates none)."""

    def __init__(self, params, where="assemble()"):
        super().__init__(params)
        self.read = set()
        self.evaluated = False
        self.where = where

    def check_read(self) -> None:
        """Refuse parameters that no integrand read (a misspelt parameter would leave the integrand
        its default silently, or fail in it with a message about something else)."""
        unread = sorted(set(self) - self.read)
        if not unread or not self.evaluated:
            return
        names = ", ".join(unread)
        who = "no integrand of the form" if self.where == "assemble()" else "its integrand never"
        raise ValueError(f"{self.where}: {who} reads the keyword(s) {names} (an integrand reads a keyword k as w.k); "
                         f"check the spelling, or leave {'it' if len(unread) == 1 else 'them'} out")


#: the attributes of :class:`QuadData` itself: keywords of :func:`assemble` with these names would be hidden
_QUAD_DATA_NAMES = frozenset({"x", "n", "h", "parent", "at", "params"})
_QUAD_DATA_NAMES_DOC = "w.x the points, w.n the normal, w.h the local size, w.parent the cells' elements, w.at, w.params"


def _quad_data(measure: Measure, quad, params, own=None):
    """QuadData of a measure's quadrature (normals and local sizes gathered per cell), with the
    form-wide ``params`` and the term's ``own``."""
    parent = quad.parent
    if quad.normal is not None:
        n = quad.normal[:, None, :]
    elif measure.normals is not None:
        n = measure.normals[parent][:, None, :]
    else:
        n = None
    for p in (params, own):
        if isinstance(p, _Params):
            p.evaluated = True
    return QuadData(quad.points, n, lambda: measure.h[parent][:, None], parent, params, own)


def _field_basis(space, measure: Measure, quad):
    """(dofs (m, k), basis fields [k]) of a field at a measure's quadrature points; on a facet
    measure k = 8 (the minus tet's four, then the plus tet's four)."""
    if measure.facets is not None:
        pairs = measure.facets.pairs[quad.parent]
        dofs, fields = [], []
        for s in (0, 1):
            el = space.local_elements(measure, pairs[:, s])
            phi = space.basis_at(quad.points, el)
            G = space.gradients_of(el)
            dofs.append(space.element_dofs[el])
            for a in range(G.shape[1]):
                b = BasisField(phi[..., a], G[:, None, a], G[:, None, a])
                fields.append(FacetField(b, ZERO) if s == 0 else FacetField(ZERO, b))
        return np.concatenate(dofs, axis=1), fields
    el = space.local_elements(measure, quad.parent)
    phi = space.basis_on(measure, quad, el)
    G = space.gradients_of(el)
    if measure.surface:
        n = quad.normal
        tG = G - np.einsum("mkd,md->mk", G, n)[..., None] * n[:, None, :]
    else:
        tG = G
    return space.element_dofs[el], [BasisField(phi[..., a], G[:, None, a], tG[:, None, a]) for a in range(G.shape[1])]



class _FieldTuple(tuple):
    """What an integrand sees on a :class:`~cutfem.fem.spaces.ProductSpace` (without ``field=``): one
    basis function per field, all :data:`ZERO` but one.  Index it (``u[0]``, ``v[1]``); used as a
    function itself (``u.grad``, ``u * v``, ``dot(u, ...)``, ``np.asarray(u)``) it raises an error
    saying so, instead of tuple arithmetic or numpy's broadcasting errors."""

    __slots__ = ()
    __array_ufunc__ = None

    def _message(self):
        return (f"on a product space u and v are tuples with one entry per field ({len(self)} fields): index them "
                "(u[0], v[1]) or integrate one field with integrand.on(measure, field=...)")

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        raise AttributeError(f"a tuple of fields has no attribute {name!r}: " + self._message())

    def _refuse(self, *args, **kwargs):
        raise TypeError(self._message())

    __add__ = __radd__ = __sub__ = __rsub__ = __mul__ = __rmul__ = __truediv__ = __rtruediv__ = _refuse
    __pow__ = __neg__ = __matmul__ = __rmatmul__ = __array__ = _refuse


def _zero_like(b):
    """The zero function in the shape of a basis function (numeric zeros, unlike :data:`ZERO`): both
    traces on a facet."""
    if isinstance(b, FacetField):
        z = _zero_like(b.minus if isinstance(b.minus, BasisField) else b.plus)
        return FacetField(z, z)
    return BasisField(np.zeros_like(b.value), np.zeros_like(b.grad), np.zeros_like(b.tgrad))
