"""Forms: integrands over measures, for one field or several, and the built-in terms.

Writing a form
--------------
A form is a sum of terms, each an integrand over a measure (:mod:`cutfem.geometry.measures`)::

    from cutfem.fem.forms import assemble, bilinear_form, dot, linear_form

    @bilinear_form(symmetric=True)
    def laplace(u, v, w):
        return dot(u.grad, v.grad)

    @bilinear_form(symmetric=True)
    def nitsche(u, v, w):                    # symmetric Nitsche on Gamma, w.h the local h_T
        return -dot(w.n, u.grad) * v - dot(w.n, v.grad) * u + w.gamma / w.h * u * v

    K = assemble(laplace * cut.dx(NEG) + nitsche * cut.ds() + 0.1 * face_jump_penalty(dg, h_power=1), V, gamma=10.0)

An integrand is a plain function of arrays shaped (cells x quadrature points).  ``u`` and ``v``
are basis functions (:class:`BasisField`): ``u.value`` (m, q), ``u.grad`` and ``u.tgrad`` (m, 1, 3)
(the gradient and, on surfaces, the tangential gradient P_h grad); arithmetic on a BasisField acts
on its value.  ``w`` (:class:`QuadData`) holds ``w.x`` (m, q, 3), ``w.n`` (m, 1, 3) the measure's
normal (n_h on Gamma_h from NEG to POS, n_F on facets from the minus to the plus tet), ``w.h``
(m, 1) the local size (h_T of the cell's tet, h_F of a facet), ``w.parent``, ``w.at(f)`` (f
evaluated at the points, once per block of cells for each function object) and the keyword
arguments given to :func:`assemble`.  Quadrature: degree 2 for a bilinear integrand, 4 for a
linear one (:func:`bilinear_form`, :func:`linear_form` say why; ``degree=`` changes it).

An integrand returns real values of shape (m, q), or (m, 1) for a value constant on each cell (a
linear one also (m, q, c): c loads at once), and it is linear in each argument, so it vanishes
when u or v is zero.  Both are checked when the form is assembled, as are finite values: an
integrand that ignores an argument (``return v``, ``return 1.0``) or returns another shape is
refused with the shapes, not summed into a wrong matrix.  Forms are scaled by real, finite
numbers.

On a facet measure each basis function has two traces: ``u.minus`` and ``u.plus`` (one of them is
zero), with :func:`jump` (minus - plus) and :func:`avg`: ``jump(u)``, ``jump(u.grad)``.

On a :class:`~cutfem.fem.spaces.ProductSpace` ``u`` and ``v`` are tuples with one entry per field, all
zero (:data:`ZERO`) but one, to be indexed (``u[0]``); ``uN - uP`` is then the jump across an
interface and the assembly skips every pair of fields whose integrand is identically zero.  One
form thus assembles to one block matrix.  The assembly loops only over fields and local basis pairs, never over elements;
``symmetric=True`` evaluates half the pairs and mirrors them (the first block of cells in full: an
integrand declared symmetric that is not is refused there), and a form whose integrands are all
symmetric assembles to an exactly symmetric matrix.

Built-in terms
--------------
:func:`mass`, :func:`stiffness`, :func:`tangential_stiffness`, :func:`face_jump_penalty` (J_F and
the bulk ghost penalty), :func:`edge_jump_penalty` (J_E), :func:`normal_gradient_penalty`,
:func:`nitsche` (symmetric Nitsche for Dirichlet data, with the outward normal of the field's
side), :func:`interface_nitsche` (Hansbo-Hansbo coupling) and the linear terms :func:`load`,
:func:`nitsche_load`, :func:`position_load`.  Each takes its measure (and, on a product space,
``field=``); the symmetric positive semidefinite ones are assembled as Gram matrices E^T E with
exact P1 formulas (:func:`cutfem.fem.assembly.gram`), several times faster than the general route and
exactly symmetric; the general route gives the same matrices to round-off (tested).  Strong
Dirichlet conditions: :func:`apply_dirichlet`.  The mathematics is in docs/math.md §3, §4 and
§7-§10.
"""

from __future__ import annotations

import numbers

import numpy as np
import scipy.sparse as sp

from . import assembly as _assembly
from .assembly import LatticeSum, PairSum, assemble_vector, gram, gram_sum
from ..geometry.measures import ElementVolume, FacetMeasure, Measure, MeshedSurface, SideVolume, SurfacePieces
from ..geometry.numbering import TET_EDGES, index_dtype
from ..geometry.markers import CUT, NEG, POS, SIDES
from .spaces import ProductSpace
from . import element_kernels

__all__ = [
    "ZERO",
    "BasisField",
    "FacetField",
    "QuadData",
    "Integrand",
    "Form",
    "bilinear_form",
    "linear_form",
    "assemble",
    "basis_integrals",
    "dot",
    "jump",
    "avg",
    "mass",
    "stiffness",
    "tangential_stiffness",
    "face_jump_penalty",
    "edge_jump_penalty",
    "normal_gradient_penalty",
    "nitsche",
    "interface_nitsche",
    "load",
    "nitsche_load",
    "position_load",
    "apply_dirichlet",
]


# ---------------------------------------------------------------------------------------------
# basis functions at quadrature points
# ---------------------------------------------------------------------------------------------


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
    and the user's parameters as attributes."""

    def __init__(self, x, n, h, parent, params):
        self.x, self.n, self.parent = x, n, parent
        self._h = h  # the local sizes, or a function giving them: computed only when an integrand asks
        self._params = params
        self._values = {}  # id(f) -> (f, values): f kept alive, so that its id is not reused
        self._latest = {}  # code object -> the latest function of that code given to at()

    @property
    def params(self):
        """The keywords given to :func:`assemble` (a dict; taken whole, all count as read)."""
        if isinstance(self._params, _Params):
            self._params.read.update(self._params)
        return self._params

    @property
    def h(self):
        if callable(self._h):
            self._h = self._h()
        return self._h

    def __getattr__(self, name):
        params = self.__dict__.get("_params", {})
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
    """The keywords of one :func:`assemble` call, with the names the integrands read (``read``) and
    whether any integrand was evaluated (``evaluated``: a measure with no cells evaluates none)."""

    def __init__(self, params):
        super().__init__(params)
        self.read = set()
        self.evaluated = False

    def check_read(self) -> None:
        """Refuse keywords that no integrand read (a misspelt parameter would leave the integrand
        its default silently, or fail in it with a message about something else)."""
        unread = sorted(set(self) - self.read)
        if not unread or not self.evaluated:
            return
        names = ", ".join(unread)
        raise ValueError(f"assemble(): no integrand of the form reads the keyword(s) {names} (an integrand reads a "
                         f"keyword k as w.k); check the spelling, or leave {'it' if len(unread) == 1 else 'them'} out")


#: the attributes of :class:`QuadData` itself: keywords of :func:`assemble` with these names would be hidden
_QUAD_DATA_NAMES = frozenset({"x", "n", "h", "parent", "at", "params"})
_QUAD_DATA_NAMES_DOC = "w.x the points, w.n the normal, w.h the local size, w.parent the cells' elements, w.at, w.params"


def _quad_data(measure: Measure, quad, params):
    """QuadData of a measure's quadrature (normals and local sizes gathered per cell)."""
    parent = quad.parent
    if quad.normal is not None:
        n = quad.normal[:, None, :]
    elif measure.normals is not None:
        n = measure.normals[parent][:, None, :]
    else:
        n = None
    if isinstance(params, _Params):
        params.evaluated = True
    return QuadData(quad.points, n, lambda: measure.h[parent][:, None], parent, params)


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


# ---------------------------------------------------------------------------------------------
# integrands, terms, forms
# ---------------------------------------------------------------------------------------------


class Integrand:
    """A bilinear ``f(u, v, w)`` or linear ``f(v, w)`` integrand; ``integrand * measure`` is a :class:`Form`."""

    __array_ufunc__ = None  # ndarray * integrand defers to __rmul__, which asks for a measure

    def __init__(self, function, linear: bool, symmetric: bool = False, degree: int | None = None):
        self.function = function
        self.linear = linear
        self.symmetric = symmetric
        self.degree = degree if degree is not None else (4 if linear else 2)
        self.__doc__ = function.__doc__
        self.__name__ = getattr(function, "__name__", "integrand")

    def __call__(self, *args):
        return self.function(*args)

    def __mul__(self, measure):
        if not isinstance(measure, Measure):
            raise TypeError(f"multiply an integrand by a measure (cut.dx(NEG), cut.ds(), cut.dF(...)), not {type(measure).__name__}")
        return Form([(1.0, _IntegrandTerm(self, measure))], self.linear)

    __rmul__ = __mul__

    def on(self, measure, field=None):
        """The form of this integrand over ``measure`` for one field of a product space (``field`` a
        position or name): the integrand then sees that field's basis functions alone."""
        return Form([(1.0, _IntegrandTerm(self, measure, field))], self.linear)


def bilinear_form(function=None, *, symmetric=False, degree=None):
    """Decorator turning ``f(u, v, w)`` into a bilinear :class:`Integrand`, integrated by
    quadrature of degree 2 unless ``degree`` is given.

    Why 2, where :func:`linear_form` takes 4: the usual bilinear integrand is a product of two P1
    functions or their gradients with coefficients constant on each cell (u v, grad u . grad v,
    w.gamma / w.h u v), a polynomial of degree at most 2 that degree 2 integrates exactly; a higher
    degree would give the same matrix at twice the points or more.  A coefficient that varies in
    space (``w.at(f) * u * v``) makes it no polynomial: pass ``degree=4`` (or more) for it, as the
    linear forms do for their data."""
    if function is None:
        return lambda f: Integrand(f, False, symmetric, degree)
    return Integrand(function, False, symmetric, degree)


def linear_form(function=None, *, degree=None):
    """Decorator turning ``f(v, w)`` into a linear :class:`Integrand`, integrated by quadrature of
    degree 4 unless ``degree`` is given.

    Why 4, where :func:`bilinear_form` takes 2: a linear integrand carries data, f v with f a
    general function (a source, boundary values), which no rule integrates exactly; degree 4 keeps
    the quadrature error of smooth data at O(h^4) per unit volume, far below the O(h^2) of P1
    (:func:`load` and :func:`nitsche_load` use 4 as well).  The two defaults are kept apart, not
    unified: either change would alter the published numbers (degree 2 for the loads) or double
    the points of every bilinear form for the same matrix (degree 4)."""
    if function is None:
        return lambda f: Integrand(f, True, False, degree)
    return Integrand(function, True, False, degree)


class Form:
    """A sum of terms with coefficients; bilinear or linear (``linear``).  ``+``, ``-`` and scalar
    ``*`` combine forms; :meth:`assemble` (or :func:`assemble`) gives the matrix or vector.

    A coefficient is one real, finite number (a Python or numpy number, or a 0-d array): strings,
    complex numbers, arrays, nan and inf are refused where the product is written, not found in the
    matrix later; coefficients that vary in space go into the integrand."""

    __array_ufunc__ = None  # ndarray * form defers to Form.__rmul__ (which refuses arrays) instead of making an object array

    def __init__(self, terms, linear: bool):
        self.terms = list(terms)
        self.linear = linear

    def _check(self, other):
        if not isinstance(other, Form):
            raise TypeError(f"can only add forms to forms, not {type(other).__name__}")
        if other.linear != self.linear:
            raise TypeError("cannot add a linear form and a bilinear form")
        return other

    def __add__(self, other):
        if isinstance(other, (int, float)) and other == 0:  # sum() starts from 0
            return self
        other = self._check(other)
        return Form(self.terms + other.terms, self.linear)

    __radd__ = __add__

    def __sub__(self, other):
        return self + (-1.0) * self._check(other)

    def __mul__(self, c):
        if isinstance(c, (Form, Integrand, Measure)) or (isinstance(c, np.ndarray) and c.ndim > 0):
            raise TypeError(f"forms are scaled by numbers, not by {type(c).__name__}; coefficients that vary go into the integrand")
        c = _number("a form's coefficient", c)
        return Form([(c * a, t) for a, t in self.terms], self.linear)

    __rmul__ = __mul__

    def __neg__(self):
        return (-1.0) * self

    def assemble(self, space, **params):
        return assemble(self, space, **params)


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


class _IntegrandTerm:
    """``integrand * measure``, for all fields of a space or (``field``) one; ``check(space)``, if
    given, is called before anything is evaluated (a built-in form's rule on the space).

    The integrand is evaluated for one pair of local basis functions (or one test function) at a
    time, on arrays (m, q); each value is checked (:func:`_integrand_values`): real, of shape
    (m, q) or (m, 1) ((m, q, c) for a linear form), finite in sum.  On the first block of cells the
    form must also vanish with its arguments (:meth:`_check_vanishes`): a(0, v) = a(u, 0) = 0, l(0) = 0
    -- an integrand that ignores u or v (``return v``, ``return 1.0``) would otherwise be summed
    over every basis pair as if it were a product."""

    def __init__(self, integrand: Integrand, measure: Measure, field=None, check=None):
        self.integrand, self.measure, self.field, self.check = integrand, measure, field, check

    def _field_pairs(self, space, w):
        """The (trial, test) field pairs (or test fields, linear) that the integrand couples."""
        fields = space.fields if isinstance(space, ProductSpace) else [space]
        if self.field is not None or len(fields) == 1:
            k = _field_index(space, self.field)
            return [(k, k)] if not self.integrand.linear else [k]
        nf = len(fields)

        def probe(k):
            return _FieldTuple(_PROBE if i == k else ZERO for i in range(nf))

        def couples(*args):
            try:
                return self.integrand(*args, w) is not ZERO
            except Exception:  # an integrand that cannot run on probes: assume it couples
                return True

        if self.integrand.linear:
            return [j for j in range(nf) if couples(probe(j))]
        return [(i, j) for i in range(nf) for j in range(nf) if couples(probe(i), probe(j))]

    def _wrap(self, space, k, basis):
        """The argument an integrand sees: the bare basis function, or a tuple on a product space."""
        if not isinstance(space, ProductSpace) or self.field is not None:
            return basis
        return _FieldTuple(basis if i == k else ZERO for i in range(len(space.fields)))

    def _evaluate(self, *args):
        """The integrand at ``args``; an error raised inside it gets a note (Python 3.11+) with the
        shapes it was given, since most slips in an integrand surface as numpy's broadcasting errors."""
        try:
            return self.integrand(*args)
        except Exception as error:
            note = getattr(error, "add_note", None)
            if note is not None:
                m, q = args[-1].x.shape[:2]
                facets = self.measure.facets is not None
                note(f"in the integrand {self.integrand.__name__!r} over {self.measure.name!r}: u.value, v.value have shape "
                     f"(m, q) = {(m, q)}, u.grad, u.tgrad (m, 1, 3), w.x (m, q, 3), w.n (m, 1, 3) or None, w.h (m, 1)"
                     + ("; on facets u.minus, u.plus with jump(u), avg(u)" if facets else "")
                     + ("; on a product space u and v are tuples, u[k]" if isinstance(args[0], _FieldTuple) else "")
                     + f"; the result must have shape {(m, q)} or (m, 1)" + (" or (m, q, c)" if self.integrand.linear else ""))
            raise

    def _check_vanishes(self, space, trial_field, test_field, trial, test, w):
        """A clear error if the integrand does not vanish when its trial (bilinear) or test function is
        the zero function: it then does not depend on that argument, or not linearly (``return v``,
        ``return 1.0``, ``(u - 1) * v``).  Evaluated once per field pair, on the first block, with a
        real basis function for the other argument; an integrand that cannot run on zeros is left to
        the evaluation that follows."""
        f = self.integrand
        kind = "linear" if f.linear else "bilinear"
        if f.linear:
            cases = [("v", "test", (self._wrap(space, test_field, _zero_like(test)), w))]
        else:
            cases = [("u", "trial", (self._wrap(space, trial_field, _zero_like(trial)), self._wrap(space, test_field, test), w)),
                     ("v", "test", (self._wrap(space, trial_field, trial), self._wrap(space, test_field, _zero_like(test)), w))]
        for name, role, args in cases:
            try:
                with np.errstate(all="ignore"):
                    val = f(*args)
                    if val is ZERO:
                        continue
                    value = np.asarray(_value(val))
                    # nan and inf are left to the check of finite values, which names them
                    vanishes = value.dtype.kind not in "biuf" or not np.any(np.isfinite(value) & (value != 0))
            except Exception:
                continue
            if not vanishes:
                example = "f * v" if f.linear else "u * v"
                raise ValueError(f"the {kind} integrand {f.__name__!r} does not vanish for {name} = 0: it does not depend on the "
                                 f"{role} function {name} (or not linearly); a {kind} integrand is linear in "
                                 f"{'v' if f.linear else 'u and in v'}: multiply by {name}, e.g. return {example}")

    def contributions(self, space, params):
        """Local vectors (linear) or matrices (bilinear) of the term, block by block of the measure's
        cells (:meth:`~cutfem.geometry.measures.Measure.blocks`): the points, basis values and integrand
        values of one block at a time.  The coupled field pairs are found, and checked, on the first block."""
        if self.check is not None:
            self.check(space)
        pairs = None
        for _, quad in self.measure.blocks(self.integrand.degree):
            w = _quad_data(self.measure, quad, params)
            first = pairs is None
            if first:
                pairs = self._field_pairs(space, w)
            yield from self._block(space, quad, w, pairs, first)

    def _block(self, space, quad, w, pairs, first):
        measure = self.measure
        weights = quad.weights
        cache = {}

        def basis(k):
            if k not in cache:
                cache[k] = _field_basis(_field(space, k), measure, quad)
            return cache[k]

        f = self.integrand
        if f.linear:
            for j in pairs:
                dofs, fields = basis(j)
                if first:
                    self._check_vanishes(space, None, j, None, fields[0], w)
                local = []
                for b in fields:
                    val = self._evaluate(self._wrap(space, j, b), w)
                    if val is ZERO:
                        local.append(None)
                        continue
                    val = _integrand_values(f, val, weights.shape)
                    local.append(np.einsum("mq...,mq->m...", np.broadcast_to(val, weights.shape + val.shape[2:]), weights))
                if all(x is None for x in local):
                    continue
                shape = next(x for x in local if x is not None).shape
                local = np.stack([np.zeros(shape) if x is None else x for x in local], axis=1)
                _finite_sums(f, measure, local)
                yield j, dofs, local
            return
        # symmetric=True evaluates half the pairs and mirrors them; the first block is evaluated in
        # full, and a form declared symmetric that is not is refused there (_check_symmetric)
        symmetric = f.symmetric and not first
        full = {}
        for i, j in pairs:  # i: trial field, j: test field
            if symmetric and (j, i) in pairs and i > j:
                continue  # mirrored from (j, i)
            dofs_u, trial = basis(i)
            dofs_v, test = basis(j)
            if first:
                self._check_vanishes(space, i, j, trial[0], test[0], w)
            blocks = np.zeros((weights.shape[0], len(test), len(trial)))
            same = i == j
            for b, vb in enumerate(test):
                for a, ua in enumerate(trial):
                    if symmetric and same and a < b:
                        continue
                    val = self._evaluate(self._wrap(space, i, ua), self._wrap(space, j, vb), w)
                    if val is ZERO:
                        continue
                    blocks[:, b, a] = np.einsum("mq,mq->m", np.broadcast_to(_integrand_values(f, val, weights.shape), weights.shape), weights)
                    if symmetric and same:
                        blocks[:, a, b] = blocks[:, b, a]
            _finite_sums(f, measure, blocks)
            if first and f.symmetric:
                full[i, j] = blocks
            yield i, j, dofs_u, dofs_v, blocks
            if symmetric and i != j and (j, i) in pairs:
                yield j, i, dofs_v, dofs_u, blocks.transpose(0, 2, 1)
        if full:
            self._check_symmetric(space, full)

    def _check_symmetric(self, space, full):
        """A clear error if an integrand declared symmetric gives a(phi_a, phi_b) != a(phi_b, phi_a)
        on the first block of cells (``full``: its local matrices per (trial, test) field pair), or
        couples two fields one way only: mirrored, it would be assembled silently into another,
        symmetric, matrix (an advection term b . grad u v, or u_0 v_1)."""
        name = self.integrand.__name__
        product = isinstance(space, ProductSpace) and self.field is None
        for (i, j), blocks in full.items():
            where = f" between fields {i} and {j}" if product and i != j else (f" on field {i}" if product else "")
            fix = ("drop symmetric=True (the matrix is then assembled as the integrand gives it) or write the integrand "
                   "symmetric in u and v")
            if (j, i) not in full:
                raise ValueError(f"the bilinear integrand {name!r} is declared symmetric (bilinear_form(symmetric=True)) but is not "
                                 f"symmetric: it couples fields {i} and {j} one way only (trial field {i}, test field {j}); {fix}")
            other = full[j, i].transpose(0, 2, 1)
            scale = max(np.abs(blocks).max(initial=0.0), np.abs(other).max(initial=0.0))
            differ = np.abs(blocks - other).max(initial=0.0)
            if differ > 1e-10 * scale:
                raise ValueError(f"the bilinear integrand {name!r} is declared symmetric (bilinear_form(symmetric=True)) but is not "
                                 f"symmetric{where}: a(u, v) and a(v, u) differ by {differ:.3g} on its first cells, where the local "
                                 f"matrices reach {scale:.3g}; {fix}")


def _integrand_values(f: Integrand, val, shape) -> np.ndarray:
    """The value an integrand returned, as an array that broadcasts to the quadrature's ``shape``
    (m, q) without reading the cell axis wrongly: real, of shape (m, q) or (m, 1) (one value per
    cell), for a linear form also (m, q, c) or (m, 1, c); anything else is an error with the
    expected and the actual shape."""
    try:
        value = np.asarray(_value(val))
    except TypeError as error:  # a tuple of fields returned as it is
        raise TypeError(f"the integrand {f.__name__!r} returned a tuple of fields: {error}") from None
    if value.dtype.kind == "c":
        raise TypeError(f"the integrand {f.__name__!r} returned complex values; only real forms are supported")
    if value.dtype.kind not in "biuf":
        raise TypeError(f"the integrand {f.__name__!r} returned {type(val).__name__}, not real values at the quadrature points")
    m, q = shape
    if value.ndim == 0:
        raise ValueError(f"the {'linear' if f.linear else 'bilinear'} integrand {f.__name__!r} returned the single number "
                         f"{value.item()!r}, not values at the quadrature points (shape (m, q) = {(m, q)} or (m, 1)): an "
                         "integrand depends on its basis functions (u * v, dot(u.grad, v.grad)); a term that vanishes "
                         "for this pair of fields is ZERO (cutfem.fem.forms.ZERO), and so is a sum of ZERO terms")
    if value.ndim not in ((2, 3) if f.linear else (2,)) or value.shape[0] != m or value.shape[1] not in (1, q):
        expected = f"(m, q) = {(m, q)} or (m, 1)" + (", or (m, q, c) for c loads at once" if f.linear else "")
        raise ValueError(f"the {'linear' if f.linear else 'bilinear'} integrand {f.__name__!r} must return one value per cell "
                         f"and quadrature point, shape {expected}; got shape {value.shape}")
    return value


def _finite_sums(f: Integrand, measure: Measure, local: np.ndarray) -> None:
    """A clear error if the integrated values of a block (m, ...) are not all finite."""
    if not np.isfinite(local).all():  # one flat pass; the per-cell count only on failure
        finite = np.isfinite(local.reshape(len(local), -1)).all(axis=1)
        raise ValueError(f"the integrand {f.__name__!r} gave non-finite values (nan or inf) on {np.count_nonzero(~finite)} "
                         f"cells of the measure {measure.name!r}")


class _GramTerm:
    """A built-in bilinear term assembled on one field by ``build(space) -> CSR``; with
    ``summed=True`` by ``build(space, into)``, ``into`` the field's running sum (:func:`_sums`: a
    :class:`~cutfem.fem.assembly.LatticeSum` on a structured box, a :class:`~cutfem.fem.assembly.PairSum`
    on a triangulated surface, None otherwise) that the build adds what it can into, returning the
    rest as CSR (or None)."""

    def __init__(self, build, field=None, summed=False):
        self.build, self.field, self.summed = build, field, summed


class _VectorTerm:
    """A built-in linear term assembled on one field by ``build(space) -> (n,) or (n, c)``."""

    def __init__(self, build, field=None):
        self.build, self.field = build, field


def _field_index(space, field):
    """The position of ``field`` in ``space``: a name of a product space's fields, or a position
    0..n-1 (an integer: not a bool, a float or a negative number); None for the only field."""
    if isinstance(space, ProductSpace):
        nf = len(space.fields)
        if field is None:
            if nf == 1:
                return 0
            raise ValueError(f"on a product space of {nf} fields, give field= (a position or one of {space.names})")
        try:
            return space.index(field)  # a name, or a position checked there
        except ValueError as exc:
            raise ValueError(f"field={field!r}: {exc}") from None
    if field is not None and (isinstance(field, (bool, np.bool_)) or field != 0):
        raise ValueError(f"field={field!r} given for a single field (a space that is not a ProductSpace)")
    return 0


def _diagonal_block(A, offset: int, n: int) -> sp.csr_matrix:
    """The n x n CSR matrix with the square CSR ``A`` as its diagonal block at rows and columns
    ``offset``: its row pointers padded and its column indices shifted (no sort, no sum of
    duplicates, unlike a detour through COO)."""
    A = sp.csr_matrix(A)
    m = A.shape[0]
    indptr = np.concatenate([np.zeros(offset, dtype=A.indptr.dtype), A.indptr, np.full(n - offset - m, A.indptr[-1], dtype=A.indptr.dtype)])
    out = sp.csr_matrix((A.data, A.indices + offset, indptr), shape=(n, n))
    out.has_sorted_indices = A.has_sorted_indices
    return out


def _field(space, k):
    return space.fields[k] if isinstance(space, ProductSpace) else space


def assemble(form: Form, space, **params):
    """The matrix (bilinear form: CSR, n x n over all fields of ``space``) or the vector (linear form:
    (n,) or (n, c)) of ``form`` on ``space`` (one field or a :class:`~cutfem.fem.spaces.ProductSpace`).
    ``params`` are handed to the integrands as attributes of ``w``; the names of its own attributes
    (x, n, h, parent, at, params) are refused, since ``w`` would show its own value instead, and so
    is a keyword that no integrand reads (a form of built-in terms only, or a misspelt name: a
    ValueError after the integrands ran, unless none ran because the measures have no cells).

    The arguments are checked first: a form (not an integrand, a measure or a space) and a space."""
    if isinstance(form, Integrand):
        raise TypeError("an integrand needs a measure: assemble(integrand * measure, space)")
    if isinstance(form, Measure):
        raise TypeError(f"assemble needs a form, got the measure {form!r}: multiply it by an integrand "
                        "(integrand * measure) or give it to a built-in term, e.g. mass(measure)")
    if not isinstance(form, Form):
        if isinstance(space, Form):
            raise TypeError("assemble(form, space): the arguments are swapped")
        raise TypeError(f"assemble needs a form (a sum of integrand * measure and built-in terms), got {type(form).__name__}")
    if not (isinstance(space, ProductSpace) or (hasattr(space, "n_dofs") and hasattr(space, "element_dofs"))):
        raise TypeError(f"assemble(form, space) needs the space of the fields (CutP1Space, SurfaceP1Space or ProductSpace), got {space!r}")
    hidden = sorted(k for k in params if k in _QUAD_DATA_NAMES or k.startswith("_"))
    if hidden:
        raise ValueError(f"assemble(): the keyword(s) {', '.join(hidden)} would be hidden by the quadrature data's own w."
                         f"{hidden[0]} ({_QUAD_DATA_NAMES_DOC}); give the parameter another name")
    if params and not any(isinstance(term, _IntegrandTerm) for _, term in form.terms):
        raise ValueError(f"assemble(): the keyword(s) {', '.join(sorted(params))} are handed to integrands as w.<name>, and "
                         "this form has only built-in terms, which take their parameters where they are made (e.g. "
                         "nitsche(ds, gamma=20)); leave them out")
    params = _Params(params)
    offsets = space.offsets if isinstance(space, ProductSpace) else np.array([0, space.n_dofs])
    n = int(offsets[-1])
    if form.linear:
        out = None
        for c, term in form.terms:
            if isinstance(term, _VectorTerm):
                k = _field_index(space, term.field)
                parts = [(k, None, c * np.asarray(term.build(_field(space, k)), dtype=float))]
            else:
                parts = [(j, dofs, c * local) for j, dofs, local in term.contributions(space, params)]
            for k, dofs, vals in parts:
                if out is None:
                    out = np.zeros((n,) + vals.shape[2 if dofs is not None else 1:])
                if dofs is None:
                    out[offsets[k] : offsets[k + 1]] += vals
                else:
                    assemble_vector(dofs, vals, int(offsets[k + 1] - offsets[k]), out=out[offsets[k] : offsets[k + 1]])
        params.check_read()
        return np.zeros(n) if out is None else out
    rows, cols, data = [], [], []
    total = None
    symmetric = True
    sums = {}  # field -> the running sum its summed terms share (c_1 a_1 + c_2 a_2: one set of arrays)

    def add(A, k):
        nonlocal total
        if len(offsets) > 2:
            A = _diagonal_block(A, int(offsets[k]), n)
        total = A if total is None else total + A

    for c, term in form.terms:
        if isinstance(term, _GramTerm):
            k = _field_index(space, term.field)
            V = _field(space, k)
            if term.summed:
                if k not in sums:
                    sums[k] = _sums(V)
                A = term.build(V, None if sums[k] is None else sums[k].scaled(c))
            else:
                A = term.build(V)
            if A is not None:
                add(c * A if c != 1.0 else A, k)
            continue
        symmetric = symmetric and term.integrand.symmetric
        for i, j, dofs_u, dofs_v, blocks in term.contributions(space, params):
            m, kv, ku = blocks.shape
            rows.append(np.broadcast_to((dofs_v + offsets[j])[:, :, None], blocks.shape).reshape(-1))
            cols.append(np.broadcast_to((dofs_u + offsets[i])[:, None, :], blocks.shape).reshape(-1))
            data.append(c * blocks.reshape(-1))
    params.check_read()
    for k, into in sums.items():
        if into is not None and into.used:
            add(into.matrix(), k)
    if rows:
        A = sp.coo_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
        if symmetric:  # the sums of duplicates run in different orders for (i, j) and (j, i)
            A = 0.5 * (A + A.T).tocsr()
        total = A if total is None else total + A
    if total is None:
        return sp.csr_matrix((n, n))
    return total.tocsr()


# ---------------------------------------------------------------------------------------------
# built-in terms
# ---------------------------------------------------------------------------------------------


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


def _kuhn_stiffness(space, volumes, into):
    """sum_T |T ∩ side| G_T G_T^T over all the tets of a structured box's element set, into ``into``
    (:class:`~cutfem.fem.assembly.LatticeSum`): the gradients of Kuhn tet l are KUHN_GRADIENTS[l] /
    spacing (:attr:`~cutfem.geometry.mesh.StructuredBox.gradient_table`), so the products G_i . G_j form a
    (6, 4, 4) table and each tet's entries are a row of it times its volume."""
    G = space.elements.background.gradient_table
    D = np.einsum("lid,ljd->lij", G, G)
    edges, diagonal = D[:, TET_EDGES[:, 0], TET_EDGES[:, 1]], D[:, np.arange(4), np.arange(4)]
    into.add_elements(space.element_dofs, edges, diagonal, types=space.elements.kuhn_types, weights=volumes)


def _sums(space):
    """The running sum of the summed terms on ``space``: a :class:`~cutfem.fem.assembly.PairSum` on a
    triangulated surface (:class:`~cutfem.fem.spaces.SurfaceP1Space`), a
    :class:`~cutfem.fem.assembly.LatticeSum` when the dofs are nodes of a structured box (a cut space
    on a :class:`~cutfem.geometry.box.StructuredBox`), else None."""
    if hasattr(space, "edge_stencil_pattern"):
        return PairSum(space)
    es = getattr(space, "elements", None)
    if getattr(es, "kuhn_types", None) is None or getattr(space, "node_ids", None) is None:
        return None
    return LatticeSum(space.node_ids, es.background)


def _same_elements(space, measure) -> bool:
    return measure.elements is space.elements


def _same_mesh(space, measure: MeshedSurface, what: str) -> None:
    """A clear error unless the field lives on the measure's surface mesh: a
    :class:`~cutfem.fem.spaces.SurfaceP1Space` of that mesh (the same object, or a mesh with the same
    points and triangles).  The closed forms on a triangulated surface read the field's mesh only,
    so a measure on another mesh would be ignored silently."""
    mesh = getattr(space, "mesh", None)
    if mesh is None:
        raise ValueError(f"{what} over the triangles of a surface mesh needs SurfaceP1Space(mesh) of that mesh; got {space!r}")
    other = measure.mesh
    if mesh is not other and not (np.array_equal(mesh.points, other.points) and np.array_equal(mesh.triangles, other.triangles)):
        raise ValueError(f"{what}: the measure is over {other!r}, but the field lives on another mesh (other points or "
                         f"triangles), {mesh!r}; integrate over mesh.ds() of the field's own mesh")


def _require(measure, kinds, what):
    if not isinstance(measure, kinds):
        names = " or ".join(k.__name__ for k in (kinds if isinstance(kinds, tuple) else (kinds,)))
        raise TypeError(f"{what} integrates over a {names} measure, got {measure!r}")


def mass(measure: Measure, field=None) -> Form:
    """(u, v) over ``measure``, exact for P1: on S_h of a cut per piece (:func:`_piece_mass`), on a triangulated surface in closed form,
    over a volume of a structured box's element set per lattice edge for the whole tets
    (:func:`_kuhn_volume_mass`), otherwise on each simplex T of the measure (triangles of S_h,
    sub-tets of a side, whole tets) with the basis values Lambda at its vertices,
    M_T = Lambda^T |T|/((k)(k+1)) (I + 1 1^T) Lambda."""

    def build(space, into):
        if isinstance(measure, MeshedSurface):
            _same_mesh(space, measure, "mass")
            return _meshed_mass(space, into)
        if isinstance(measure, SurfacePieces):
            if _same_elements(space, measure):
                return _piece_mass(space, into)
            c = measure.cut
            el = space.local_elements(measure, c.triangle_tets)
            return _simplex_mass(space, c.triangle_points, el, c.triangle_areas)
        if isinstance(measure, (SideVolume, ElementVolume)):
            if _same_elements(space, measure) and into is not None:
                return _kuhn_volume_mass(space, measure, into)
        if isinstance(measure, SideVolume):
            vertices = measure.cell_vertices()
            return _simplex_mass(space, vertices, space.local_elements(measure, measure.cell_parent), measure.cell_volumes)
        if isinstance(measure, ElementVolume):
            es = measure.elements
            return _simplex_mass(space, es.vertices, space.local_elements(measure, np.arange(es.n_elements)), es.volumes)
        raise TypeError(f"mass integrates over cells (a surface or a volume), not over {measure!r}")

    return Form([(1.0, _GramTerm(build, field, summed=True))], False)


def _kuhn_volume_mass(space, measure, into):
    """The volume mass matrix over the cells of a side (or of whole tets) of a structured box's
    element set: the whole elements' M_T = |T|/20 (1 + delta_ij) summed per lattice edge into
    ``into`` (:class:`~cutfem.fem.assembly.LatticeSum`: no basis values, no Gram product); returns the
    sub-tets of the cut elements by :func:`_simplex_mass` (None if there are none)."""
    w = measure.whole_cells
    into.add_elements(space.element_dofs, np.full(6, 1.0 / 20.0), np.full(4, 1.0 / 10.0), weights=space.elements.volumes,
                      elements=measure.whole_elements)
    if measure.n_cells > w:
        sub, parent = measure.sub_tets
        return _simplex_mass(space, sub, parent, measure.sub_volumes)
    return None


def _piece_mass(space, into=None):
    """The exact surface mass matrix of a cut space on its own cut tets: into ``into`` (a
    :class:`~cutfem.fem.assembly.LatticeSum`) triangle by triangle of S_h
    (:meth:`~cutfem.fem.assembly.LatticeSum.add_pieces`: no per-tet arrays, 112 bytes a cut tet), else
    the element matrices M_K = int_{S_K} lambda_i lambda_j of :func:`_piece_moments` summed by
    :func:`_element_symmetric`.  The same matrix as the triangle route (:func:`_simplex_mass`) to
    round-off either way (tested)."""
    if into is not None:
        c = space.cut
        table, types = space.gradient_lookup()
        into.add_pieces(c.vertices, c.triangles, c.triangle_tets, c.triangle_areas, space.dof_points, space.element_dofs,
                        table, types, space.element_dofs)
        return None
    edges, diagonal, _ = _piece_moments(space.cut)
    return _element_symmetric(space, slice(None), edges, diagonal, into)


def _piece_moments(cut):
    """(edges (m, 6), diagonal (m, 4), integrals (m, 4)) for the m cut tets (the element set CUT, in
    its order): the exact piece mass matrices M_K by their entries on the local edges
    (:data:`~cutfem.geometry.numbering.TET_EDGES`) and diagonal, and int_{S_K} lambda_i; one compiled pass over
    the triangles of S_h (:func:`cutfem.fem.element_kernels.piece_moments`)."""

    es = cut.elements(CUT)
    table, types = es.gradient_lookup()
    return element_kernels.piece_moments(cut.vertices, cut.triangles, cut.triangle_tets, cut.triangle_areas, es.points, es.tets,
                                 table, types)


def _element_symmetric(space, el, edges, diagonal, into=None):
    """sum_K A_K of symmetric 4 x 4 element matrices on the field's elements ``el`` (an index or a
    slice), given by their entries on the local edges ``edges`` (m, 6) (:data:`~cutfem.geometry.numbering.TET_EDGES`
    order) and their ``diagonal`` (m, 4): added into ``into`` (a :class:`~cutfem.fem.assembly.LatticeSum`
    of a structured box: no sort; returns None), or as one COO matrix when ``into`` is None.
    Exactly symmetric either way."""
    dofs = space.element_dofs[el]
    if into is not None:
        into.add_elements(dofs, edges, diagonal)
        return None
    i, j = TET_EDGES[:, 0], TET_EDGES[:, 1]
    rows = np.concatenate([dofs[:, i].ravel(), dofs[:, j].ravel(), dofs.ravel()])
    cols = np.concatenate([dofs[:, j].ravel(), dofs[:, i].ravel(), dofs.ravel()])
    values = np.concatenate([edges.ravel(), edges.ravel(), diagonal.ravel()])
    A = sp.coo_matrix((values, (rows, cols)), shape=(space.n_dofs, space.n_dofs)).tocsr()
    return (0.5 * (A + A.T)).tocsr()  # the sums of duplicates run in different orders for (i, j) and (j, i)


def stiffness(measure: Measure, field=None) -> Form:
    """(grad u, grad v) over a volume measure: |T ∩ side| G G^T per tet (the P1 gradients are
    constant), for a side of the cut (:class:`~cutfem.geometry.measures.SideVolume`) or whole tets; summed
    per lattice edge on a structured box (:func:`_kuhn_stiffness`), as a Gram product otherwise."""
    _require(measure, (SideVolume, ElementVolume), "stiffness")

    def build(space, into):
        es = measure.elements
        if _same_elements(space, measure):  # no gathered copy of the gradients
            if into is not None:
                return _kuhn_stiffness(space, measure.part_volumes, into)
            return _gradient_matrix(space, space.gradients_of, measure.part_volumes)
        el = space.local_elements(measure, np.arange(es.n_elements))
        return _gradient_matrix(space, lambda cells: space.gradients_of(el[cells]), measure.part_volumes, el)

    return Form([(1.0, _GramTerm(build, field, summed=True))], False)


def tangential_stiffness(measure: Measure, field=None) -> Form:
    """(P_h grad u, P_h grad v) over a surface: on each piece |K| (P_h G_j)·(P_h G_i), |K| the area
    of the piece and P_h = I - n_h n_h^T; on a triangulated surface in closed form
    (:func:`_meshed_stiffness`); on the cut tets of a structured box per lattice edge
    (:func:`_kuhn_tangential_stiffness`)."""
    _require(measure, (SurfacePieces, MeshedSurface), "tangential_stiffness")

    def build(space, into):
        if isinstance(measure, MeshedSurface):
            _same_mesh(space, measure, "tangential_stiffness")
            into.add(*_meshed_stiffness(space))
            return None
        if _same_elements(space, measure):
            if into is not None:
                return _kuhn_tangential_stiffness(space, measure, into)
            return _gradient_matrix(space, space.tangential_gradients_of, measure.piece_areas)
        es = measure.elements
        el = space.local_elements(measure, np.arange(es.n_elements))
        G, n = space.gradients_of(el), measure.normals
        tG = G - np.einsum("mkd,md->mk", G, n)[..., None] * n[:, None, :]
        return _gradient_matrix(space, lambda cells: tG[cells], measure.piece_areas, el)

    return Form([(1.0, _GramTerm(build, field, summed=True))], False)


def _kuhn_tangential_stiffness(space, measure, into):
    """sum_K |K| (P_h G)(P_h G)^T over the pieces of the cut tets of a structured box, into
    ``into`` (:class:`~cutfem.fem.assembly.LatticeSum`).  G is the row of the tet's Kuhn type in the
    (6, 4, 3) gradient table, so with c = G n_h the entries are |K| (G_a . G_b - c_a c_b), per tet
    in one compiled pass (:func:`cutfem.fem.element_kernels.tangential_entries`): no (m, 4, 3) gradients and no
    sparse Gram product (at spacing 0.0125, 853 thousand cut tets, the Gram route took 0.40 s,
    this one 0.05 s)."""

    table, types = space.gradient_lookup()
    m = len(types)
    edges, diagonal = np.empty((m, 6)), np.empty((m, 4))
    element_kernels.tangential_entries(np.ascontiguousarray(table, dtype=float), np.ascontiguousarray(types),
                               np.ascontiguousarray(measure.normals, dtype=float),
                               np.ascontiguousarray(measure.piece_areas, dtype=float), edges, diagonal)
    into.add_elements(space.element_dofs, edges, diagonal)


def position_load(measure: Measure, field=None) -> Form:
    """The right-hand sides of the mean curvature problem, b_ik = (grad_{S_h} x_k, grad_{S_h} phi_i)_{S_h},
    an (n, 3) array, without assembling the stiffness matrix.

    The coordinates x_k are linear, so their P1 interpolant is exact on every element and
    grad_{S_h} x_k = P_h e_k; since P_h is a symmetric projection and grad_{S_h} phi_i is tangent,
    (P_h e_k) . grad_{S_h} phi_i = (grad_{S_h} phi_i)_k.  Hence

        b_i = sum_K |S_K| grad_{S_h} phi_i|_K,

    the area-weighted tangential gradients summed per dof: the same vector as A x_k with A the
    tangential stiffness (to round-off; tested), at the cost of one compiled pass over the elements
    (:func:`cutfem.fem.element_kernels.tangential_gradient_sums`; on a triangulated surface
    :func:`cutfem.fem.element_kernels.meshed_position_load`, from the node positions alone) instead of a sparse
    matrix product.  Each element's contributions sum to |S_K| P_h grad(1) = 0, so sum_i b_i = 0
    up to round-off (the zero integral of H_h).
    """
    _require(measure, (SurfacePieces, MeshedSurface), "position_load")

    def build(space):

        if isinstance(measure, MeshedSurface):
            _same_mesh(space, measure, "position_load")
            out = np.zeros((space.n_dofs, 3))
            element_kernels.meshed_position_load(space.dof_points, space.element_dofs, out)
            return out
        if not _same_elements(space, measure):
            raise ValueError("position_load needs the field on the cut tets, CutP1Space(cut, CUT)")
        out = np.zeros((space.n_dofs, 3))
        table, types = space.gradient_lookup()
        element_kernels.tangential_gradient_sums(space.element_dofs, table, types, np.ascontiguousarray(space.element_normals, dtype=float),
                                         np.ascontiguousarray(measure.piece_areas, dtype=float), out)
        return out

    return Form([(1.0, _VectorTerm(build, field))], True)


def basis_integrals(measure: Measure, field=None) -> Form:
    """The vector (int phi_i)_i over a cell measure, i.e. (1, v): on S_h of a cut per triangle of the
    pieces, |T| lambda_i(centroid) (:func:`cutfem.fem.element_kernels.piece_integrals`, one compiled pass); on a
    triangulated surface |T|/3 per vertex; otherwise :func:`load` of 1 at degree 1 (exact for P1).
    Its sum is the measure's size; it is 1^T M for the mass matrix M over the same measure (to
    round-off), without assembling M."""
    if isinstance(measure, FacetMeasure):
        raise TypeError("basis_integrals integrates over cells (a volume or a surface), not over facets")
    _require(measure, Measure, "basis_integrals")

    def build(space):
        if isinstance(measure, MeshedSurface):
            _same_mesh(space, measure, "basis_integrals")
            return np.bincount(space.element_dofs.reshape(-1), weights=np.repeat(space.element_areas / 3.0, 3),
                               minlength=space.n_dofs)
        if isinstance(measure, SurfacePieces) and _same_elements(space, measure):

            cut, out = measure.cut, np.zeros(space.n_dofs)
            table, types = space.gradient_lookup()
            element_kernels.piece_integrals(cut.vertices, cut.triangles, cut.triangle_tets, cut.triangle_areas, space.dof_points,
                                    space.element_dofs, table, types, space.element_dofs, out)
            return out
        return assemble(load(lambda x: np.ones(x.shape[:2]), measure, degree=1), space)

    return Form([(1.0, _VectorTerm(build, field))], True)


def load(f, measure: Measure, degree: int = 4, closest_point=None, field=None) -> Form:
    """(f, v) over ``measure`` (a cell measure: a side's volume, whole tets, S_h or a triangulated
    surface) by quadrature of the given degree.

    ``f(x)`` takes points (m, q, 3) and returns real, finite values (checked) of shape (m, q) or
    (m, q, c) (then the vector is (n, c)); with ``closest_point`` (a map x -> p(x)) it is evaluated
    as f o p, the extension f^e of docs/math.md §4.
    Block by block of cells, b_{K,k} = sum_q w_q f(x_q) phi_k(x_q): one product of the weighted
    values with the basis values (the rule's own barycentric coordinates on whole elements)."""
    _require_function(f, "load: f")
    if closest_point is not None:
        _require_function(closest_point, "load: closest_point")
    g = f if closest_point is None else (lambda x: f(closest_point(x)))
    if isinstance(measure, FacetMeasure):
        raise TypeError("load integrates over cells (a volume or a surface); for a facet term write a linear_form integrand")
    _require(measure, Measure, "load")

    def local(quad, el, phi, fw):
        if phi.strides[0] == 0 and fw.ndim == 2:  # every cell whole: one basis table
            return fw @ phi[0]
        return np.einsum("mqk,mq...->mk...", phi, fw)

    return Form([(1.0, _VectorTerm(lambda space: _point_load(space, measure, degree, g, "the load f(x)", local), field))], True)


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
    once).  Faces of a structured box go into lattice slots instead (:func:`face_jump_penalty`)."""

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


def face_jump_penalty(measure: FacetMeasure, h_power: float = 0.0, field=None) -> Form:
    """sum_F h_F^a ([n_F . grad u], [n_F . grad v])_F over a facet set, with the local h_F (the
    longest edge of F) and a = ``h_power``.

    [n_F . grad u] = n_{F,T1}.grad u|T1 + n_{F,T2}.grad u|T2 with outward unit face normals; for P1
    it is constant on F, so the integral is |F| times the product of jumps.  Over the interior faces
    of the cut tets with a = 0 this is the face stabilization J_F of the mean curvature problem
    (docs/math.md §3); over the ghost faces of a side with a = 1 it is the Burman-Hansbo ghost
    penalty of a bulk field (§7), to be multiplied by gamma_g.  ``h_power`` is one real, finite
    number for which every h_F^a is a finite, nonzero float (else a ValueError).  An empty facet set
    gives the zero matrix.

    Meaningful coefficients (the problems check them, :mod:`cutfem.problems.common`).  As a ghost
    penalty (a = 1) beside a stiffness both scale as h^3 per tet, so gamma_g is a number: about
    0.01-1; its consistency error grows with it and it locks u_h to linear functions across the
    ghost faces as it grows (poisson-cut's L2 error 10 times the default's at 1e6).  As J_F beside a
    surface mass matrix (entries O(s^2) at spacing s, J_F's O(h^a)) the weight tau_F s^a counts:
    below 1e-3 the small pieces are barely controlled (the error grows like its inverse), below
    1e-6 not at all; above 1e6 s^2 the mass is lost beside it in round-off."""
    _require(measure, FacetMeasure, "face_jump_penalty")
    h_power = _number("h_power", h_power)

    def build(space, into):
        f = measure.facets
        if f.n_facets == 0:
            return None  # nothing to add: the zero matrix, as a user form over the same facets gives
        if measure.elements is space.elements:
            pairs = f.pairs
        else:
            pairs = np.stack([space.local_elements(measure, f.pairs[:, s]) for s in (0, 1)], axis=1)
        if into is not None:  # face-adjacent tets of a structured box: normals and areas computed face by face
            table, types = space.gradient_lookup()
            into.add_face_jumps(pairs, f.opposite, np.ones(1) if h_power == 0 else _h_power(f.h, h_power, "face_jump_penalty"),
                                space.elements.volumes, space.element_dofs, table, types)
            return None
        n, scale = f.normals_areas()
        if h_power != 0:
            scale *= _h_power(f.h, h_power, "face_jump_penalty")
        return _jump_gram(space, pairs, n, n, -1.0, scale)

    return Form([(1.0, _GramTerm(build, field, summed=True))], False)


def edge_jump_penalty(measure: Measure, h: float | None = None, field=None) -> Form:
    """J_E(u, v) = sum_E h ([t_E . grad u], [t_E . grad v])_E over the edges of a surface, between
    neighbouring pieces of S_h (cut) or triangles (meshed).

    [t_E . grad u] = t_{E,K1} . grad u|K1 + t_{E,K2} . grad u|K2 with the outward conormals of the
    two surface elements; constant on E for P1, so the integral is |E| times the product of jumps.
    ``h`` defaults to the field's global mesh size (docs/math.md §3 asks for exactly that value);
    either must be a positive number."""
    _require(measure, (SurfacePieces, MeshedSurface), "edge_jump_penalty")
    if h is not None:
        _positive(h=h)

    def build(space, into):
        hh = space.h if h is None else h
        _positive(h=hh)
        if isinstance(measure, MeshedSurface):
            _same_mesh(space, measure, "edge_jump_penalty")
            into.add(*_meshed_edge_penalty(space, hh))
            return None
        if not _same_elements(space, measure):
            raise ValueError("edge_jump_penalty needs the field on the cut tets, CutP1Space(cut, CUT)")
        c = measure.cut
        t = c.surface_edge_conormals
        # the pieces along an edge of S_h need not lie in face-adjacent tets: Gram products, not lattice slots
        return _jump_gram(space, c.surface_edge_tets, t[:, 0], t[:, 1], 1.0, hh * c.surface_edge_lengths)

    return Form([(1.0, _GramTerm(build, field, summed=True))], False)


def normal_gradient_penalty(measure: ElementVolume, h_power: float = 1.0, field=None) -> Form:
    """s(u, v) = sum_T h_T^a (n_h . grad u, n_h . grad v)_T over whole tets that carry a normal n_h
    (the cut tets: ``cut.dx(CUT)``), with the local h_T and a = ``h_power`` (one real, finite number
    for which every h_T^a is a finite, nonzero float, else a ValueError; multiply by tau_N)."""
    _require(measure, ElementVolume, "normal_gradient_penalty")
    h_power = _number("h_power", h_power)
    if measure.normals is None:
        raise ValueError("normal_gradient_penalty needs tets with a normal n_h: integrate over cut.dx(CUT)")

    def build(space):
        es = measure.elements
        el = space.local_elements(measure, np.arange(es.n_elements))
        c = np.einsum("mkd,md->mk", space.gradients_of(el), measure.normals)
        rows = c * np.sqrt(_h_power(es.h, h_power, "normal_gradient_penalty") * es.volumes)[:, None]
        return gram(space.element_dofs[el], rows, space.n_dofs)

    return Form([(1.0, _GramTerm(build, field))], False)


def _side_of(space):
    """NEG or POS for a bulk field on one side's element set of its cut (``CutP1Space(cut, NEG)`` or
    ``CutP1Space(cut, POS)``: the set is the cut's own, :meth:`~cutfem.geometry.cut.CutMesh.elements`), else
    None (the cut tets, another element set, a surface mesh)."""
    cut, es = getattr(space, "cut", None), getattr(space, "elements", None)
    side = getattr(es, "name", None)
    if cut is None or side not in SIDES:
        return None
    return side if cut.elements(side) is es else None


def _outward_sign(space, measure: SurfacePieces, what: str) -> float:
    """The outward unit normal of the field's side on Gamma_h is ``sign * n_h`` (n_h points from NEG
    to POS): +1 for a field of NEG, -1 for a field of POS.  A clear error for a field that is not a
    bulk field of one side of the measure's cut: its outward normal is not defined."""
    side = _side_of(space)
    if side is None or space.cut is not measure.cut:
        raise ValueError(f"{what} imposes a condition on Gamma_h for a bulk field of one side of the same cut, "
                         f"CutP1Space(cut, NEG) or CutP1Space(cut, POS); got {space!r}")
    return 1.0 if side == NEG else -1.0


def nitsche(measure: SurfacePieces, gamma: float = 10.0, field=None) -> Form:
    """Symmetric Nitsche terms for u = g on Gamma (Burman-Hansbo, docs/math.md §8):

        -(n . grad u, v)_Gamma - (u, n . grad v)_Gamma + (gamma / h) (u, v)_Gamma,

    n the outward unit normal of the field's domain and h the local h_T of the cut tet.  The side
    comes from the field: n = n_h (from NEG to POS) for ``CutP1Space(cut, NEG)``, n = -n_h for
    ``CutP1Space(cut, POS)`` (the outer domain); any other field is refused (:func:`_outward_sign`).
    The matching right-hand side is :func:`nitsche_load`.  gamma (a positive number) must exceed an
    inverse-estimate constant, or the matrix is indefinite; the solver reports that.

    Exact for P1, per cut tet K with the piece S_K (area |S|, centroid c): grad u is constant and
    int_{S_K} lambda_i = |S| lambda_i(c), so the element matrix is

        N_K = -(p g^T + g p^T) + (gamma / h_T) M_K,   p_i = |S| lambda_i(c),  g_j = n . grad lambda_j,

    with M_K the exact piece mass matrix and p from :func:`_piece_moments`, summed by
    :func:`_element_symmetric` (exactly symmetric).  The same matrix as the integrand with quadrature of degree 2 to
    round-off (tested)."""
    _positive(gamma=gamma)
    _require(measure, SurfacePieces, "nitsche")

    def build(space, into):
        sign = _outward_sign(space, measure, "nitsche")
        cut = measure.cut
        edges, diagonal, p = _piece_moments(cut)
        es = cut.elements(CUT)
        el = space.local_elements(measure, np.arange(es.n_elements))
        g = np.einsum("mkd,md->mk", space.gradients_of(el), es.normals)
        if sign < 0:
            g = -g
        scale = (gamma / es.h)[:, None]
        i, j = TET_EDGES[:, 0], TET_EDGES[:, 1]
        edges = edges * scale - (p[:, i] * g[:, j] + g[:, i] * p[:, j])
        diagonal = diagonal * scale - 2.0 * p * g
        return _element_symmetric(space, el, edges, diagonal, into)

    return Form([(1.0, _GramTerm(build, field, summed=True))], False)


def nitsche_load(g, measure: SurfacePieces, gamma: float = 10.0, field=None) -> Form:
    """The Nitsche right-hand side of u = g on Gamma: -(g, n . grad v)_Gamma + (gamma / h) (g, v)_Gamma,
    with ``g(x)`` evaluated at the quadrature points of Gamma_h (degree 4; docs/math.md §8) and n the
    outward normal of the field's side, as in :func:`nitsche`.  ``g`` returns (m, q) or, for a
    vector-valued field, (m, q, c) (the vector is then (n, c)); its values must be real and finite.

    Block by block of the triangles of S_h, with weights w_q, basis values phi_k and the constant
    n . grad phi_k of the cut tet: b_k = sum_q w_q g(x_q) (gamma / h_T phi_k(x_q) - n . grad phi_k)."""
    _positive(gamma=gamma)
    _require(measure, SurfacePieces, "nitsche_load")
    _require_function(g, "nitsche_load: g")
    degree = 4

    def build(space):
        sign = _outward_sign(space, measure, "nitsche_load")

        def local(quad, el, phi, gw):
            dn = sign * np.einsum("mkd,md->mk", space.gradients_of(el), quad.normal)
            penalty = (gamma / measure.h[quad.parent]).reshape((-1,) + (1,) * (gw.ndim - 1))
            return np.einsum("mqk,mq...->mk...", phi, gw * penalty) - np.einsum("mk,m...->mk...", dn, gw.sum(axis=1))

        return _point_load(space, measure, degree, g, "nitsche_load: g(x)", local)

    return Form([(1.0, _VectorTerm(build, field))], True)


def interface_nitsche(measure: SurfacePieces, a_neg: float, a_pos: float, gamma: float = 10.0, weights: str = "harmonic",
                      fields=(0, 1)) -> Form:
    """The Nitsche coupling of two fields across Gamma (Hansbo-Hansbo, docs/math.md §9):

        -({a n . grad u}, [v]) - ([u], {a n . grad v}) + (lambda / h) ([u], [v])   over Gamma_h,

    [w] = w_NEG - w_POS, {w} = k_NEG w_NEG + k_POS w_POS, n from NEG to POS and h the local h_T.
    ``weights="harmonic"``: k_NEG = a_POS / (a_NEG + a_POS) (and k_POS = 1 - k_NEG), robust in the
    contrast; ``weights="volume"``: k_i = |T ∩ Omega_i| / |T| per cut tet.  The penalty is
    lambda = 2 gamma (k_NEG^2 a_NEG + k_POS^2 a_POS), the weight that bounds the flux average by the
    energy of both sides; for harmonic weights it equals gamma times the harmonic mean
    2 a_NEG a_POS / (a_NEG + a_POS).

    ``fields = (f_NEG, f_POS)`` (positions or names) are the NEG field, then the POS field, of a
    :class:`~cutfem.fem.spaces.ProductSpace`: ``CutP1Space(cut, NEG)`` and ``CutP1Space(cut, POS)`` of
    the measure's cut.  The rule is checked when the form is assembled, never adapted: two fields in
    the other order, the same field twice, a field of another element set or a single space are
    refused with the fix (e.g. ``fields=(1, 0)`` for ``ProductSpace(V_pos, V_neg)``)."""
    _require(measure, SurfacePieces, "interface_nitsche")
    _positive(a_neg=a_neg, a_pos=a_pos, gamma=gamma)
    if isinstance(fields, str) or np.ndim(fields) != 1 or len(fields) != 2:
        raise ValueError(f"fields must be a pair (NEG field, POS field) of positions or names, got {fields!r}")
    if weights == "harmonic":
        k_neg = np.full(measure.elements.n_elements, a_pos / (a_neg + a_pos))
    elif weights == "volume":
        k_neg = measure.side_fraction(NEG)
    else:
        raise ValueError(f"weights must be 'harmonic' or 'volume', got {weights!r}")
    k_pos = 1.0 - k_neg
    lam = 2.0 * gamma * (k_neg**2 * a_neg + k_pos**2 * a_pos)
    at = {}  # the positions of the NEG and the POS field in the space being assembled (set by check)

    def check(space):
        if not isinstance(space, ProductSpace):
            raise TypeError(f"interface_nitsche couples two fields: assemble it on ProductSpace(V_neg, V_pos), not on {space!r}")
        k = [_field_index(space, f) for f in fields]
        if k[0] == k[1]:
            raise ValueError(f"interface_nitsche: fields={tuple(fields)!r} names the same field twice; give the NEG field, "
                             "then the POS field, e.g. fields=(0, 1)")
        sides = [_side_of(space.fields[i]) if getattr(space.fields[i], "cut", None) is measure.cut else None for i in k]
        if sides != [NEG, POS]:
            where = ", ".join(f"field {f!r} on {getattr(getattr(space.fields[i], 'elements', None), 'name', space.fields[i])!r}"
                              for f, i in zip(fields, k))
            fix = (f"pass fields=({fields[1]!r}, {fields[0]!r})" if sides == [POS, NEG] else
                   "give the fields CutP1Space(cut, NEG) and CutP1Space(cut, POS) of the measure's cut")
            raise ValueError(f"interface_nitsche: fields=(f_NEG, f_POS) must name the NEG field, then the POS field, of "
                             f"the measure's cut; got {where}: {fix}")
        at["neg"], at["pos"] = k

    @bilinear_form(symmetric=True)
    def coupling(u, v, w):
        i_neg, i_pos = at["neg"], at["pos"]
        kn, kp, penalty = k_neg[w.parent][:, None], k_pos[w.parent][:, None], lam[w.parent][:, None] / w.h
        un, up, vn, vp = u[i_neg], u[i_pos], v[i_neg], v[i_pos]
        flux_u = kn * a_neg * dot(w.n, un.grad) + kp * a_pos * dot(w.n, up.grad)
        flux_v = kn * a_neg * dot(w.n, vn.grad) + kp * a_pos * dot(w.n, vp.grad)
        ju, jv = un - up, vn - vp
        return -flux_u * jv - flux_v * ju + penalty * ju * jv

    return Form([(1.0, _IntegrandTerm(coupling, measure, check=check))], False)


def _number(name: str, value) -> float:
    """``value`` as a float if it is one real, finite number (a Python or numpy number, or a 0-d
    array); a TypeError for anything else (a string, a complex number, an array), a ValueError for
    nan and inf."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    if not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__} {value!r}")
    if not np.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def _h_power(h: np.ndarray, a: float, what: str) -> np.ndarray:
    """h^a of the local sizes h (> 0), or a ValueError naming ``what`` when some h^a is not a finite
    positive float64: a power that overflows (h^a = inf, a matrix of inf and NaN) or underflows
    (h^a = 0, the term silently gone) for the sizes of this mesh."""
    with np.errstate(over="ignore", under="ignore"):
        s = h**a
    if not (np.all(np.isfinite(s)) and np.all(s > 0)):
        raise ValueError(f"{what}: h^a with a = h_power = {a!r} is not a finite positive number for the local h in "
                         f"[{h.min():.3g}, {h.max():.3g}] (it overflows or underflows in float64); choose a power a for "
                         "which h^a is finite and nonzero")
    return s


def _positive(**values):
    """Each keyword a real, finite, positive number, or an error naming it: a TypeError for what is
    not one real number (:func:`_number`), a ValueError for nan, inf, zero and negative numbers."""
    for name, value in values.items():
        try:
            ok = _number(name, value) > 0
        except ValueError:
            ok = False
        if not ok:
            raise ValueError(f"{name} must be a positive number, got {value!r}")


def apply_dirichlet(K, b, dofs, values):
    """Strong Dirichlet conditions u[dofs] = values, by symmetric elimination in place of the rows.

    Returns ``(K_bc, b_bc)`` of the same size: the rows and columns of ``dofs`` are replaced by
    d_i e_i^T (d_i = |K_ii|, or 1 where K_ii = 0), b_bc = b - K[:, dofs] g outside ``dofs`` and
    b_bc = d_i g_i on them.  K_bc stays symmetric (positive definite when K is on the other dofs),
    its solution carries the prescribed values, and the dof numbering (hence a multigrid hierarchy)
    is unchanged.  Why d_i and not 1: an iterative solver stops on |b - K x| <= tol |b|, and unit
    rows make the Dirichlet values part of |b| at their own scale, unrelated to K's.  With a small
    coefficient (the interface problem at a_POS = 1e-3, where g ~ 1 / a_POS and K ~ a_POS) the
    values dwarfed the interior equations and CG stopped with those unsolved (inside L2 error 0.27
    against 0.087 at spacing 0.05); rows at K's own scale keep every equation weighed alike.

    ``dofs``: integer dof numbers in [0, n), in any order (``values[i]`` goes with ``dofs[i]``; a dof
    given twice must have the same value twice), or a boolean mask of length n, which stands for
    ``np.flatnonzero(mask)`` (the values then go with the masked dofs in increasing order).
    ``values``: a number (every dof, every column), or one row per dof, shape (len(dofs),) + b.shape[1:]
    (b is (n,) or (n, c)); real and finite.  Anything else is refused with the shapes."""
    K = sp.csr_matrix(K)
    n = K.shape[0]
    if K.shape != (n, n):
        raise ValueError(f"K must be square, got shape {K.shape}")
    b = np.asarray(b, dtype=float)
    if b.ndim not in (1, 2) or len(b) != n:
        raise ValueError(f"b must have shape ({n},) or ({n}, c) for K of shape {K.shape}, got {b.shape}")
    dofs = np.asarray(dofs)
    if dofs.dtype == bool:
        if dofs.shape != (n,):
            raise ValueError(f"a boolean mask of Dirichlet dofs must have shape ({n},), got {dofs.shape}")
        dofs = np.flatnonzero(dofs)
    elif dofs.size == 0:
        dofs = np.zeros(0, dtype=np.int64)
    elif dofs.dtype.kind not in "iu":
        raise TypeError(f"Dirichlet dofs must be integer dof numbers (or a boolean mask of length {n}), got {dofs.dtype} values")
    if dofs.ndim != 1:
        raise ValueError(f"Dirichlet dofs must be a 1-d array of dof numbers, got shape {dofs.shape}")
    if dofs.size and (dofs.min() < 0 or dofs.max() >= n):
        raise ValueError(f"Dirichlet dofs must lie in [0, {n})")
    rows = (dofs.size,) + b.shape[1:]
    values = np.asarray(values)
    if values.dtype.kind not in "biuf":
        raise TypeError(f"Dirichlet values must be real numbers, got {values.dtype} values")
    values = np.broadcast_to(values.astype(float), rows) if values.ndim == 0 else values.astype(float)
    if values.shape != rows:
        raise ValueError(f"Dirichlet values must be a number or have shape {rows} (one row per dof of dofs, "
                         f"{dofs.size} of them), got {values.shape}")
    if not np.all(np.isfinite(values)):
        raise ValueError("Dirichlet values must be finite (no nan or inf)")
    dofs, first, which = np.unique(dofs, return_index=True, return_inverse=True)
    g_dofs = values[first]  # the values in the order of the sorted dofs: each stays with its dof
    if len(dofs) < len(which):
        differ = np.flatnonzero(np.any((values != g_dofs[which]).reshape(len(which), -1), axis=1))
        if differ.size:
            d = dofs[which[differ[0]]]
            raise ValueError(f"Dirichlet dof {d} is given twice with different values, {g_dofs[which[differ[0]]]} and "
                             f"{values[differ[0]]}")
    g = np.zeros((n,) + b.shape[1:])
    g[dofs] = g_dofs
    keep = np.ones(n)
    keep[dofs] = 0.0
    scale = np.zeros(n)
    diagonal = np.abs(K.diagonal()[dofs])
    scale[dofs] = np.where(diagonal > 0, diagonal, 1.0)  # the rows of the eliminated dofs: d_i e_i^T
    D = sp.diags(keep)
    column = (n,) + (1,) * (b.ndim - 1)
    b_bc = keep.reshape(column) * (b - K @ g) + scale.reshape(column) * g
    K_bc = (D @ K @ D + sp.diags(scale)).tocsr()
    return K_bc, b_bc


# ---------------------------------------------------------------------------------------------
# Closed forms on a triangulated surface (SurfaceP1Space).  On a flat triangle T with edge vectors
# e_k = x_{k+1} - x_k (indices mod 3) every P1 integral is a rational function of |T| and the dot
# products S_k = e_k . e_k, Q_k = e_k . e_{k+1} (SurfaceMesh.triangle_edge_dots).  Arrays of shape
# (M, 3) are indexed by the half-edge 3 t + k (local edge k of triangle t, from vertex k to k + 1,
# which is also the corner of vertex k); the half-edge after it in the triangle is the column
# rotated by one, X[:, _NEXT] (the edge penalty's passes are compiled).  Each matrix is a diagonal plus one
# value per pair of nodes, summed by cutfem.fem.assembly.PairSum and written straight into the cached
# CSR structure of the node graph or the edge stencil (cutfem.fem.assembly.SymmetricPattern): no
# quadrature, no sort, no sparse sum, exactly symmetric.  The general
# routes above give the same matrices to round-off (tested).
# ---------------------------------------------------------------------------------------------

_NEXT = [1, 2, 0]


def _meshed_mass(space, into) -> None:
    """Exact P1 mass matrix of S_h, added into ``into`` (:class:`~cutfem.fem.assembly.PairSum`):
    M_T = |T|/12 (I + 1 1^T), i.e.

        M_ii = sum_{T at i} |T| / 6,   M_ij = sum_{T at edge ij} |T| / 12.
    """
    areas = space.element_areas
    diagonal = np.bincount(space.element_dofs.reshape(-1), weights=np.repeat(areas / 6.0, 3), minlength=space.n_dofs)
    et = space.mesh.edge_triangles
    into.add(diagonal, (areas[et[:, 0]] + areas[et[:, 1]]) / 12.0)


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
