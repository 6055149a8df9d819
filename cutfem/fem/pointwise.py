"""What an integrand sees at the quadrature points: basis functions, their traces and the quadrature data.

An integrand (:mod:`cutfem.fem.forms`) is called on arrays shaped (cells x quadrature points): the
basis functions ``u`` and ``v`` (:class:`BasisField`: ``value`` (m, q), ``grad`` and ``tgrad``
(m, 1, 3) for P1, (m, q, 3) for P2 or on a deformed geometry, ``hess`` (m, 1, 3, 3) of P2 and
:data:`ZERO` of P1; of a vector field :class:`VectorBasisField`: ``value`` (m, q, 3), ``grad`` (m, 1, 3, 3)
with the components as rows, ``div``, ``sym_grad``, ``curl``), on a facet their two traces
(:class:`FacetField`, with :func:`jump` and :func:`avg`), on a product space a tuple with one entry
per field, all :data:`ZERO` but one, and ``w`` (:class:`QuadData`): the points, the measure's
normal, the local size, ``w.at(f)`` and the term's parameters.  Every array keeps the two leading
axes (cells, points; 1 for what is constant on a cell) before its tensor axes, so :func:`dot` and
:func:`inner` read a value's rank from its number of axes.  This module makes those values from a
space, a measure and its quadrature, and checks what a user function returns at the points.
"""

from __future__ import annotations

import numbers

import numpy as np

from ..geometry.measures import Measure
from .spaces import RealSpace, VectorSpace

__all__ = ["ZERO", "BasisField", "VectorBasisField", "FacetField", "QuadData", "dot", "inner", "jump", "avg"]


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


class _Later:
    """A value computed when first asked for (``get()``), then kept: the Hessians of a block's basis,
    which only the integrands of second derivatives read."""

    __slots__ = ("_make", "_value")

    def __init__(self, make):
        self._make, self._value = make, None

    def get(self):
        if self._make is not None:
            self._value, self._make = self._make(), None
        return self._value


def _resolved(h):
    """``h`` itself, or its value if it is a :class:`_Later`."""
    return h.get() if isinstance(h, _Later) else h


class BasisField:
    """A basis function at quadrature points: ``value`` (m, q), ``grad``, ``tgrad`` (m, 1, 3) for P1
    (constant on a cell), (m, q, 3) for P2 or on a deformed geometry (``tgrad`` also with the
    per-point normals of a deformed surface), ``hess`` (m, 1, 3, 3) of P2 (constant on a tet) and
    :data:`ZERO` of P1 (so that terms of second derivatives cost nothing there); arithmetic acts on
    ``value``.  ``hess`` may be given as a :class:`_Later`, computed when an integrand first reads it."""

    __slots__ = ("value", "grad", "tgrad", "_hess")

    def __init__(self, value, grad, tgrad, hess=None):
        self.value, self.grad, self.tgrad = value, grad, tgrad
        self._hess = ZERO if hess is None else hess

    @property
    def hess(self):
        return _resolved(self._hess)

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


class VectorBasisField:
    """A basis function phi e_c of a vector field (component ``c`` of the P1 function ``phi``) at
    quadrature points: ``value`` (m, q, 3), ``grad`` (m, 1, 3, 3) with the components as rows,
    (grad u)_ij = d u_i / d x_j, ``tgrad`` the rows' tangential gradients (grad u P_h on a surface),
    ``div`` (m, 1), ``sym_grad`` (m, 1, 3, 3) = (grad u + grad u^T) / 2, ``curl`` (m, 1, 3), and
    ``u[i]`` the component i (m, q).  Scaled by numbers and scalar values ((m, q), (m, 1) or a
    scalar basis function); added to vector values (m, q, 3); products of two vectors are written
    :func:`dot` or :func:`inner`, so that a vector never enters a scalar form by broadcasting.

    Made from the scalar ``phi`` (m, q), its gradient ``g`` (m, 1, 3) and tangential gradient; the
    arrays with the zero components are made when first asked for, and kept for the other basis
    pairs of the block (an integrand of ``u.div`` never allocates the 3 x 3 gradients)."""

    __slots__ = ("phi", "g", "tg", "h", "component", "_value", "_grad", "_tgrad")
    __array_ufunc__ = None  # ndarray op field defers to the reflected operators below (no broadcasting of (m, 1) against 3)

    def __init__(self, phi, grad, tgrad, component: int, hess=None):
        self.phi, self.g, self.tg, self.component = phi, grad, tgrad, component
        self.h = ZERO if hess is None else hess
        self._value = self._grad = self._tgrad = None

    @property
    def value(self):
        if self._value is None:
            self._value = np.zeros(self.phi.shape + (3,))
            self._value[..., self.component] = self.phi
        return self._value

    def _rows(self, g):
        out = np.zeros(g.shape[:2] + (3, 3))
        out[:, :, self.component] = g
        return out

    @property
    def grad(self):
        if self._grad is None:
            self._grad = self._rows(self.g)
        return self._grad

    @property
    def tgrad(self):
        if self._tgrad is None:
            self._tgrad = self._rows(self.tg)
        return self._tgrad

    @property
    def hess(self):
        """(m, 1, 3, 3, 3) the Hessians of the components (component first), of P2; ZERO of P1."""
        if self.h is ZERO:
            return ZERO
        h = _resolved(self.h)
        out = np.zeros(h.shape[:2] + (3, 3, 3))
        out[:, :, self.component] = h
        return out

    @property
    def div(self):
        return self.g[..., self.component]

    @property
    def sym_grad(self):
        return 0.5 * (self.grad + np.swapaxes(self.grad, -1, -2))

    @property
    def curl(self):
        return np.cross(self.g, np.eye(3)[self.component])  # curl(phi e_c) = grad phi x e_c

    def __getitem__(self, i):
        return self.phi if i == self.component else np.zeros_like(self.phi)

    def __array__(self, dtype=None, copy=None):
        return np.asarray(self.value, dtype=dtype)

    @staticmethod
    def _scalar(other):
        """``other`` as a factor of the value (m, q, 3): a number, or scalar values with a new last axis."""
        if isinstance(other, BasisField):
            other = other.value
        if isinstance(other, numbers.Number):
            return other
        if isinstance(other, (VectorBasisField, _Traces)) or np.ndim(other) > 2:
            raise TypeError("a vector basis function times a vector: the products of two vectors are dot(u, v) and inner(u, v); "
                            "a vector is scaled by numbers and scalar values (m, q) or (m, 1)")
        other = np.asarray(other)
        return other[..., None] if other.ndim == 2 else other

    def __mul__(self, other):
        if isinstance(other, _Zero):
            return other * self
        return self.value * self._scalar(other)

    __rmul__ = __mul__

    def __truediv__(self, other):
        if isinstance(other, _Zero):
            return other * self
        return self.value / self._scalar(other)

    @staticmethod
    def _vector(other):
        other = other.value if isinstance(other, VectorBasisField) else other
        if isinstance(other, (BasisField, numbers.Number)) or (np.ndim(other) != 1 and np.ndim(other) < 3):
            raise TypeError("a vector basis function is added to vector values (m, q, 3) or a constant vector (3,), not to scalars")
        return other

    def __add__(self, other):
        if isinstance(other, _Zero):
            return other + self
        return self.value + self._vector(other)

    __radd__ = __add__

    def __sub__(self, other):
        if isinstance(other, _Zero):
            return other + self  # the probe stays the probe, ZERO leaves self
        return self.value - self._vector(other)

    def __rsub__(self, other):
        if isinstance(other, _Zero):
            return other - self
        return self._vector(other) - self.value

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

    @property
    def tgrad(self):
        return _Traces(self.minus.tgrad, self.plus.tgrad)

    @property
    def div(self):
        return _Traces(self.minus.div, self.plus.div)

    @property
    def sym_grad(self):
        return _Traces(self.minus.sym_grad, self.plus.sym_grad)

    @property
    def hess(self):
        return _Traces(self.minus.hess, self.plus.hess)


def _value(a):
    return a.value if isinstance(a, (BasisField, VectorBasisField)) else a


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


def _rank(a) -> int:
    """The tensor rank of a value: its axes after the two leading ones (cells, points); a 1-d
    array is a constant vector, a number a scalar."""
    n = np.ndim(_value(a))
    return n if n < 2 else n - 2


def _zero_aware(a, b):
    """ZERO when a factor is ZERO, the probe when a factor is the probe (finding the coupled fields), else None."""
    if isinstance(a, _Zero) or isinstance(b, _Zero):
        return ZERO if (a is ZERO or b is ZERO) else _PROBE
    return None


def dot(a, b):
    """The contraction of the last axis of ``a`` with the first tensor axis of ``b`` (zero-aware):
    u . v of vectors, A v and v A of a matrix and a vector, A B of matrices.  Vectors and scalar
    values are contracted over their last axis as they always were (the same bits)."""
    zero = _zero_aware(a, b)
    if zero is not None:
        return zero
    ra, rb = _rank(a), _rank(b)
    if ra <= 1 and rb <= 1:
        return np.einsum("...d,...d->...", a, b)
    a, b = _value(a), _value(b)
    if ra == 2 and rb == 1:
        return np.einsum("...ij,...j->...i", a, b)
    if ra == 1 and rb == 2:
        return np.einsum("...i,...ij->...j", a, b)
    if ra == 2 and rb == 2:
        return np.einsum("...ij,...jk->...ik", a, b)
    raise TypeError(f"dot of values of ranks {ra} and {rb}: dot contracts vectors and matrices (at most rank 2)")


def inner(a, b):
    """The full contraction of two values of one rank (zero-aware): a b of scalars, u . v of
    vectors, A : B = sum_ij A_ij B_ij of matrices."""
    zero = _zero_aware(a, b)
    if zero is not None:
        return zero
    ra, rb = _rank(a), _rank(b)
    if ra != rb:
        raise TypeError(f"inner of values of ranks {ra} and {rb}: both must be scalars, vectors or matrices (use dot for A v)")
    if ra == 0:
        return _value(a) * _value(b)
    if ra == 1:
        return np.einsum("...d,...d->...", _value(a), _value(b))
    if ra == 2:
        return np.einsum("...ij,...ij->...", _value(a), _value(b))
    raise TypeError(f"inner of values of rank {ra}: at most rank 2 (matrices)")


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
    """What an integrand sees besides the basis functions: ``x`` (m, q, 3), ``n`` (m, 1, 3) (per cell) or
    (m, q, 3) (per point, on a deformed surface) or None,
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
        n = quad.point_normals  # (m, 1, 3) per cell or (m, q, 3) per point (a deformed surface)
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
    measure k = 8 (the minus tet's four, then the plus tet's four).  A vector field has the
    scalar basis times each unit vector, component after component (k = 3 x the scalar k, its dofs
    c n + the scalar dofs); a real field its one function, 1 everywhere (on a facet both traces)."""
    if isinstance(space, RealSpace):
        m = quad.weights.shape[0]
        one = BasisField(np.ones((m, 1)), np.zeros((m, 1, 3)), np.zeros((m, 1, 3)))
        return np.zeros((m, 1), dtype=np.int64), [FacetField(one, one) if measure.facets is not None else one]
    if isinstance(space, VectorSpace):
        dofs, fields = _field_basis(space.scalar, measure, quad)
        n = space.scalar.n_dofs
        return (np.concatenate([dofs + c * n for c in range(3)], axis=1),
                [_component(b, c) for c in range(3) for b in fields])
    if measure.facets is not None:
        pairs = measure.facets.pairs[quad.parent]
        points = quad.points if quad.reference_points is None else quad.reference_points
        dofs, fields = [], []
        for s in (0, 1):
            el = space.local_elements(measure, pairs[:, s])
            phi, G, H = _basis_derivatives(space, measure, quad, el, points=points, cells=pairs[:, s])
            dofs.append(space.element_dofs[el])
            for a in range(G.shape[2]):
                b = BasisField(phi[..., a], G[:, :, a], G[:, :, a], _column(H, a))
                fields.append(FacetField(b, ZERO) if s == 0 else FacetField(ZERO, b))
        return np.concatenate(dofs, axis=1), fields
    el = space.local_elements(measure, quad.parent)
    phi, G, H = _basis_derivatives(space, measure, quad, el)
    if measure.surface:  # the tangential part at each point, with the cell's normal or (deformed) the point's
        n = quad.point_normals
        if G.shape[1] == 1:  # P1 on a planar cell: constant gradients
            G0 = G[:, 0]
            tG = G0[:, None] - np.einsum("mkd,mqd->mqk", G0, n)[..., None] * n[:, :, None, :]
        else:
            n = np.broadcast_to(n, G.shape[:2] + (3,))
            tG = G - np.einsum("mqkd,mqd->mqk", G, n)[..., None] * n[:, :, None, :]
    else:
        tG = G
    return space.element_dofs[el], [BasisField(phi[..., a], G[:, :, a], tG[:, :, a], _column(H, a))
                                    for a in range(G.shape[2])]


def _basis_derivatives(space, measure, quad, elements, points=None, cells=None):
    """The field's (values, gradients, Hessians) (:meth:`~cutfem.fem.spaces.CutSpace.derivatives`) with
    the Hessians a :class:`_Later` (None of P1): an integrand without second derivatives never
    pays for them (on a deformed cell they are a 3 x 3 product per point and basis function)."""
    phi, G, _ = space.derivatives(measure, quad, elements, points=points, cells=cells, hessians=False)
    if getattr(space, "order", 1) < 2:
        return phi, G, None
    return phi, G, _Later(lambda: space.hessians(measure, quad, elements, G, cells, points))


def _column(H, a):
    """Basis function a's Hessians of the block's (a :class:`_Later` of (m, q, k, 3, 3), or None)."""
    return None if H is None else _Later(lambda: H.get()[:, :, a])



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


def _component(b, c):
    """The vector basis function b e_c of a scalar one (a :class:`FacetField` trace by trace)."""
    if isinstance(b, FacetField):
        return FacetField(_component(b.minus, c), _component(b.plus, c))
    if b is ZERO:
        return b
    return VectorBasisField(b.value, b.grad, b.tgrad, c, None if b._hess is ZERO else b._hess)


def _zero_like(b):
    """The zero function in the shape of a basis function (numeric zeros, unlike :data:`ZERO`): both
    traces on a facet."""
    if isinstance(b, FacetField):
        z = _zero_like(b.minus if not isinstance(b.minus, _Zero) else b.plus)
        return FacetField(z, z)
    if isinstance(b, VectorBasisField):
        return VectorBasisField(np.zeros_like(b.phi), np.zeros_like(b.g), np.zeros_like(b.tg), b.component,
                                None if b.h is ZERO else _Later(lambda: np.zeros_like(_resolved(b.h))))
    return BasisField(np.zeros_like(b.value), np.zeros_like(b.grad), np.zeros_like(b.tgrad),
                      None if b._hess is ZERO else _Later(lambda: np.zeros_like(b.hess)))
