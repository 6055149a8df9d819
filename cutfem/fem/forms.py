"""Forms: integrands over measures, summed with coefficients, and their assembly.

Writing a form
--------------
A form is a sum of terms, each an integrand over a measure (:mod:`cutfem.geometry.measures`)::

    from cutfem.fem.forms import assemble, bilinear_form
    from cutfem.fem.pointwise import dot

    @bilinear_form(symmetric=True)
    def laplace(u, v, w):
        return dot(u.grad, v.grad)

    @bilinear_form(symmetric=True)
    def nitsche(u, v, w):                    # symmetric Nitsche on Gamma, w.h the local h_T
        return -dot(w.n, u.grad) * v - dot(w.n, v.grad) * u + w.gamma / w.h * u * v

    K = assemble(laplace * cut.dx(NEG) + nitsche.on(cut.ds(), gamma=10.0) + 0.1 * face_jump_penalty(dg, h_power=1), V)

An integrand is a plain function of arrays shaped (cells x quadrature points), called with the
basis functions ``u``, ``v`` and the quadrature data ``w`` of :mod:`cutfem.fem.pointwise`:
``u.value`` (m, q), ``u.grad`` and ``u.tgrad`` (m, 1, 3), on facets ``u.minus``, ``u.plus`` with
``jump`` and ``avg``; ``w.x``, ``w.n``, ``w.h``, ``w.parent``, ``w.at(f)`` and the parameters.  On a
vector field (:class:`~cutfem.fem.spaces.VectorSpace`) ``u.value`` is (m, q, 3), ``u.grad`` (m, 1, 3, 3)
with ``u.div``, ``u.sym_grad``, ``u.curl``, and products are written ``dot`` and ``inner``; a
:class:`~cutfem.fem.spaces.RealSpace` field is the constant 1.
Quadrature: degree 2 for a bilinear integrand, 4 for a linear one (:func:`bilinear_form`,
:func:`linear_form` say why; ``degree=`` changes it), plus 2 (k - 1) on fields of order k
(:meth:`Integrand.degree_for`).  On P2 fields (or a deformed geometry) ``u.grad`` is (m, q, 3) and
``u.hess`` (m, 1, 3, 3) (ZERO on P1).

Parameters reach an integrand as attributes of ``w``: the term's own, bound where the term is made
(``integrand.on(measure, gamma=10.0)``, ``nitsche(ds, gamma=10.0)``), before the form-wide keywords
of :func:`assemble` (``assemble(form, V, gamma=10.0)``).  A parameter that no integrand reads is
refused, as are names that ``w``'s own attributes would hide.

An integrand returns real values of shape (m, q), or (m, 1) for a value constant on each cell (a
linear one also (m, q, c): c loads at once), and it is linear in each argument, so it vanishes
when u or v is zero.  Both are checked when the form is assembled, as are finite values: an
integrand that ignores an argument (``return v``, ``return 1.0``) or returns another shape is
refused with the shapes, not summed into a wrong matrix.  Forms are scaled by real, finite
numbers.

On a :class:`~cutfem.fem.spaces.ProductSpace` ``u`` and ``v`` are tuples with one entry per field, all
zero (``ZERO``) but one, to be indexed (``u[0]``); ``uN - uP`` is then the jump across an
interface and the assembly skips every pair of fields whose integrand is identically zero.  One
form thus assembles to one block matrix.  The assembly loops only over fields and local basis pairs, never over elements;
``symmetric=True`` evaluates half the pairs and mirrors them (the first block of cells in full: an
integrand declared symmetric that is not is refused there), and a form whose integrands are all
symmetric assembles to an exactly symmetric matrix.

Built-in terms
--------------
The terms of :mod:`cutfem.fem.terms` (``mass``, ``stiffness``, ``nitsche``, the penalties, the loads)
are integrands of this same language, not a second one beside it: each is an :class:`Integrand`
whose function is its mathematics, with its parameters bound to the term, and which carries an
exact implementation (``exact``: closed P1 formulas, Gram products, lattice sums) that
:func:`assemble` uses in place of quadrature.  A built-in term is therefore combined, scaled and
assembled like ``integrand * measure``; :meth:`Form.by_quadrature` evaluates the same form by
quadrature of the integrands alone, the reference that the exact implementations match to round-off
(tested).  A term may also advise on an indefinite matrix (:attr:`Form.indefinite_hint`: the
Nitsche term names its penalty), so a parameter enters once, where its term is made.
"""

from __future__ import annotations

import numbers

import numpy as np
import scipy.sparse as sp

from . import high_order
from .assembly import assemble_vector, running_sum
from .p2_kernels import symmetric_csr
from ..geometry.measures import Measure
from .pointwise import (_PROBE, _QUAD_DATA_NAMES, _QUAD_DATA_NAMES_DOC, ZERO, _field_basis, _FieldTuple, _Params,
                        _quad_data, _value, _zero_like)
from .spaces import ProductSpace, RealSpace, VectorSpace

__all__ = ["Integrand", "Form", "bilinear_form", "linear_form", "assemble"]


class Integrand:
    """A bilinear ``f(u, v, w)`` or linear ``f(v, w)`` integrand; ``integrand * measure`` is a :class:`Form`.

    A built-in term's integrand (:mod:`cutfem.fem.terms`) carries three more functions:

    * ``exact``, the implementation :func:`assemble` uses instead of quadrature:
      ``exact(term, space, into, scale)`` for a bilinear integrand adds ``scale`` times the term's
      matrix on the field's ``space`` into ``into`` (the field's running sum,
      :func:`~cutfem.fem.assembly.running_sum`, or None) where it can and returns the rest unscaled
      (CSR, or None); ``exact(term, space)`` for a linear one returns the vector (n,) or (n, c);
      for a term that couples fields (``couples=True``, a bilinear integrand on a product space)
      ``exact(term, space)`` returns the unscaled (n, n) matrix over all of the space's fields;
    * ``prepare(space, term)``, called before the integrand is evaluated by quadrature on ``space``
      (all fields): its checks of the space, and the parameters it derives from it (a dict,
      seen as ``w.<name>``; the side of a field for Nitsche's normal);
    * ``advice(params, form)``, the fix of an indefinite matrix of ``form`` that the term suggests
      (:attr:`Form.indefinite_hint`), or None;
    * ``high_order(term, space)``, the quadrature of a symmetric bilinear (or a linear) integrand on
      a scalar P2 field by a compiled kernel (:mod:`cutfem.fem.high_order`): (dofs, local matrices
      or vectors) block by block of cells, the matrices summed into CSR by
      :func:`~cutfem.fem.p2_kernels.symmetric_csr`; for a term on
      two fields of a product space (``fields=True``) ``high_order(term, space, offsets)`` on the
      whole space, the dofs in its numbering, or None where the fields are not P2."""

    __array_ufunc__ = None  # ndarray * integrand defers to __rmul__, which asks for a measure

    def __init__(self, function, linear: bool, symmetric: bool = False, degree: int | None = None, exact=None,
                 prepare=None, advice=None, couples: bool = False, high_order=None, fields: bool = False):
        self.function = function
        self.couples, self.fields = couples, fields
        self.linear = linear
        self.symmetric = symmetric
        self.degree = degree if degree is not None else (4 if linear else 2)
        self.exact, self.prepare, self.advice, self.high_order = exact, prepare, advice, high_order
        self.__doc__ = function.__doc__
        self.__name__ = getattr(function, "__name__", "integrand")

    def __call__(self, *args):
        return self.function(*args)

    def degree_for(self, order: int) -> int:
        """The quadrature degree on fields of polynomial ``order``: :attr:`degree` (that of P1) plus
        2 (order - 1), the higher degree of a product of two basis functions (of one basis function
        times data, with the same margin for the data)."""
        return self.degree + 2 * (max(int(order), 1) - 1)

    def __mul__(self, measure):
        return self.on(measure)

    __rmul__ = __mul__

    def on(self, measure, field=None, **params):
        """The form of this integrand over ``measure``, for one field of a product space (``field`` a
        position or name: the integrand then sees that field's basis functions alone), with the
        term's own parameters ``params`` (``w.<name>``, before the keywords of :func:`assemble`)."""
        if not isinstance(measure, Measure):
            raise TypeError(f"multiply an integrand by a measure (cut.dx(NEG), cut.ds(), cut.dF(...)), not {type(measure).__name__}")
        _check_names(params, f"{self.__name__}.on()")
        return Form([(1.0, Term(self, measure, field, params))], self.linear)

    def by_quadrature(self) -> "Integrand":
        """The same integrand without its exact implementation: evaluated by quadrature."""
        out = Integrand(self.function, self.linear, self.symmetric, self.degree, prepare=self.prepare, advice=self.advice)
        out.__name__ = self.__name__
        return out


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
    (the built-in loads of :mod:`cutfem.fem.terms` use 4 as well).  The two defaults are kept apart, not
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

    def by_quadrature(self) -> "Form":
        """The same form with every term evaluated by quadrature of its integrand, the built-in
        terms' exact implementations left aside: the reference those match to round-off (a term
        without a quadrature route, the edge penalty J_E, says so when assembled)."""
        return Form([(c, Term(t.integrand.by_quadrature(), t.measure, t.field, t.params)) for c, t in self.terms], self.linear)

    @property
    def indefinite_hint(self) -> str | None:
        """What the terms advise when the form's matrix is indefinite (for the ``indefinite_hint`` of
        :func:`cutfem.solvers.solve.solve`): the Nitsche terms name their penalty gamma and, when the
        form has no face penalty on the ghost facets, the ghost penalty it lacks; None when no term
        advises."""
        hints = []
        for c, term in self.terms:
            advice = term.integrand.advice
            hint = advice(term.params, self) if advice is not None and c != 0 else None
            if hint and hint not in hints:
                hints.append(hint)
        return "; or ".join(hints) if hints else None

    def assemble(self, space, **params):
        return assemble(self, space, **params)


class Term:
    """``integrand * measure``, for all fields of a space or (``field``) one, with the term's own
    parameters ``params``: assembled by the integrand's exact implementation when it has one
    (:func:`assemble`), else by quadrature (:meth:`contributions`).

    By quadrature the integrand's ``prepare(space, term)``, if any, is called first (its rule on
    the space, and parameters it derives from it); then the integrand is evaluated for one pair of
    local basis functions (or one test function) at a time, on arrays (m, q); each value is checked (:func:`_integrand_values`): real, of shape
    (m, q) or (m, 1) ((m, q, c) for a linear form), finite in sum.  On the first block of cells the
    form must also vanish with its arguments (:meth:`_check_vanishes`): a(0, v) = a(u, 0) = 0, l(0) = 0
    -- an integrand that ignores u or v (``return v``, ``return 1.0``) would otherwise be summed
    over every basis pair as if it were a product."""

    def __init__(self, integrand: Integrand, measure: Measure, field=None, params=None):
        self.integrand, self.measure, self.field = integrand, measure, field
        self.params = {} if params is None else dict(params)

    def field_space(self, space):
        """The space of the term's field in ``space`` (the space itself for a single field)."""
        return _field(space, _field_index(space, self.field))

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
                     f"(m, q) = {(m, q)}, u.grad, u.tgrad (m, 1, 3) (of a vector field (m, q, 3) and (m, 1, 3, 3), u.div (m, 1)), "
                     "w.x (m, q, 3), w.n (m, 1, 3) or None, w.h (m, 1)"
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
        own = _Params(self.params, f"the term {self.integrand.__name__!r} over {self.measure.name!r}")
        if self.integrand.prepare is not None:
            derived = self.integrand.prepare(space, self)
            own.update(derived)
            own.read.update(derived)
        pairs = None
        order = getattr(space if self.field is None else self.field_space(space), "order", 1)
        blocks = self.measure.blocks(self.integrand.degree_for(order)) if order < 2 else \
            self.measure.blocks(self.integrand.degree_for(order), high_order.BLOCK_CELLS)
        for _, quad in blocks:
            w = _quad_data(self.measure, quad, params, own)
            first = pairs is None
            if first:
                pairs = self._field_pairs(space, w)
            yield from self._block(space, quad, w, pairs, first)
        own.check_read()

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
                         "for this pair of fields is ZERO (cutfem.fem.pointwise.ZERO), and so is a sum of ZERO terms")
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


def _p1_field(space, k, term):
    """Field k of ``space`` for a built-in term: a P1 field (scalar or vector), not a real one."""
    V = _field(space, k)
    if isinstance(V, RealSpace):
        raise TypeError(f"the built-in term {term.integrand.__name__!r} acts on P1 fields, and field {k} is a RealSpace (one "
                        "constant): write the multiplier's terms as an integrand, e.g. u[0] * v[1] + u[1] * v[0] over dx")
    return V


def _exact_route(term, space) -> bool:
    """Whether ``term`` is assembled by its exact implementation: a built-in term on a P1 field (the
    closed forms are those of P1; on a P2 field every term goes by quadrature of its integrand) over
    a planar measure (the closed forms hold on planar cells, so a measure deformed by an
    isoparametric cut, ``measure.deformation``, takes the quadrature of the integrand instead)."""
    measure = term.measure
    deformed = getattr(measure, "deformation", None) is not None or (  # the faces of a lifted cut lift the fields on them
        measure.facets is not None and getattr(getattr(measure.elements, "cut", None), "deformation", None) is not None)
    if term.integrand.exact is None or deformed:
        return False
    fields = space if term.integrand.couples else _field(space, _field_index(space, term.field))
    return getattr(fields, "order", 1) < 2  # P1, or a real field (refused there)


def _high_order_route(term, space, offsets):
    """The term's local matrices by its compiled quadrature (``high_order``) on a scalar field of
    order 2 (or on two fields of a product space, ``fields``), as (dofs in the numbering of ``space``,
    blocks), or None (the form language evaluates it)."""
    f = term.integrand.high_order
    if f is None:
        return None
    if term.integrand.fields:
        return f(term, space, offsets)
    k = _field_index(space, term.field)
    V = _field(space, k)
    if getattr(V, "order", 1) < 2 or isinstance(V, VectorSpace):
        return None
    return ((dofs + offsets[k], blocks) for dofs, blocks in f(term, V))


def assemble(form: Form, space, **params):
    """The matrix (bilinear form: CSR, n x n over all fields of ``space``) or the vector (linear form:
    (n,) or (n, c)) of ``form`` on ``space`` (one field or a :class:`~cutfem.fem.spaces.ProductSpace`).
    ``params`` are handed to the integrands as attributes of ``w`` (after each term's own); the names
    of its own attributes (x, n, h, parent, at, params) are refused, since ``w`` would show its own
    value instead, and so is a keyword that no integrand reads (a form of built-in terms only, or a
    misspelt name: a ValueError after the integrands ran, unless none ran because the measures have
    no cells).

    Each term is assembled by its integrand's exact implementation when it has one, the field is P1
    and the measure is planar (:func:`_exact_route`), else by quadrature (at the degree of the
    field's order, :meth:`Integrand.degree_for`).  On a field of a structured box or of a triangulated
    surface the exact terms add, each times its coefficient, into one running sum of the field
    (:func:`~cutfem.fem.assembly.running_sum`), written to CSR once: c_1 a_1 + c_2 a_2 costs one
    pass, not two matrices and their sum.

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
    if not (isinstance(space, (ProductSpace, VectorSpace, RealSpace)) or (hasattr(space, "n_dofs") and hasattr(space, "element_dofs"))):
        raise TypeError(f"assemble(form, space) needs the space of the fields (CutSpace, SurfaceP1Space, VectorSpace, RealSpace or "
                        f"ProductSpace), got {space!r}")
    _check_names(params, "assemble()")
    if params and all(term.integrand.exact is not None for _, term in form.terms):
        raise ValueError(f"assemble(): the keyword(s) {', '.join(sorted(params))} are handed to integrands as w.<name>, and "
                         "this form has only built-in terms, which take their parameters where they are made (e.g. "
                         "nitsche(ds, gamma=20)); leave them out")
    params = _Params(params)
    offsets = space.offsets if isinstance(space, ProductSpace) else np.array([0, space.n_dofs])
    n = int(offsets[-1])
    if form.linear:
        out = None
        for c, term in form.terms:
            if _exact_route(term, space):
                k = _field_index(space, term.field)
                parts = [(k, None, c * np.asarray(term.integrand.exact(term, _p1_field(space, k, term)), dtype=float))]
            else:
                fast = _high_order_route(term, space, offsets)  # its dofs in the numbering of space
                parts = [(j, dofs, c * local) for j, dofs, local in term.contributions(space, params)] if fast is None else \
                    [(None, dofs, c * local) for dofs, local in fast]
            for k, dofs, vals in parts:
                if out is None:
                    out = np.zeros((n,) + vals.shape[2 if dofs is not None else 1:])
                if dofs is None:
                    out[offsets[k] : offsets[k + 1]] += vals
                elif k is None:
                    assemble_vector(dofs, vals, n, out=out)
                else:
                    assemble_vector(dofs, vals, int(offsets[k + 1] - offsets[k]), out=out[offsets[k] : offsets[k + 1]])
        params.check_read()
        return np.zeros(n) if out is None else out
    rows, cols, data = [], [], []
    total = None
    symmetric = True
    sums = {}  # field -> the running sum its exact terms share (c_1 a_1 + c_2 a_2: one set of arrays)
    local = {}  # k -> the (dofs (m, k), local matrices (m, k, k)) of the P2 built-in terms

    def add(A, k):
        nonlocal total
        if len(offsets) > 2:
            A = _diagonal_block(A, int(offsets[k]), n)
        total = A if total is None else total + A

    for c, term in form.terms:
        if _exact_route(term, space) and term.integrand.couples:
            A = term.integrand.exact(term, space)
            total = c * A if total is None else total + c * A
            continue
        if _exact_route(term, space):
            k = _field_index(space, term.field)
            V = _p1_field(space, k, term)
            if k not in sums:
                sums[k] = running_sum(V)
            A = term.integrand.exact(term, V, sums[k], c)
            if A is not None:
                add(c * A if c != 1.0 else A, k)
            continue
        fast = _high_order_route(term, space, offsets)
        if fast is not None:  # symmetric local matrices, summed by one compiled pass a width
            for dofs, blocks in fast:
                local.setdefault(blocks.shape[1], []).append((dofs, c * blocks if c != 1.0 else blocks))
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
    for parts in local.values():
        A = symmetric_csr(np.concatenate([d for d, _ in parts]), np.concatenate([b for _, b in parts]), n)
        total = A if total is None else total + A
    if rows:
        A = sp.coo_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
        if symmetric:  # the sums of duplicates run in different orders for (i, j) and (j, i)
            A = 0.5 * (A + A.T).tocsr()
        total = A if total is None else total + A
    if total is None:
        return sp.csr_matrix((n, n))
    return total.tocsr()


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


def _check_names(params, where: str) -> None:
    """Refuse parameters that ``w``'s own attributes (or private names) would hide."""
    hidden = sorted(k for k in params if k in _QUAD_DATA_NAMES or k.startswith("_"))
    if hidden:
        raise ValueError(f"{where}: the keyword(s) {', '.join(hidden)} would be hidden by the quadrature data's own w."
                         f"{hidden[0]} ({_QUAD_DATA_NAMES_DOC}); give the parameter another name")
