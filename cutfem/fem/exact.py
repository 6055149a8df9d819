"""Exact fields from sympy expressions: manufactured solutions and their data.

An :class:`Exact` is a scalar, vector (3,) or matrix (3, 3) field given by sympy expressions in the
coordinates x, y, z.  Its derivatives are exact (symbolic), and calling it on points of shape
(..., 3) evaluates it with numpy (``sympy.lambdify``, common subexpressions shared) to shape
(..., *shape)::

    import cutfem as cf
    u = cf.Exact(["sin(pi*x)*y", "z", "x*y"])     # a velocity
    p = cf.Exact("x*y*z")                          # a pressure
    f = -0.1 * u.laplacian + p.grad                # the Stokes load for nu = 0.1
    f(points)                                      # (n, 3)

The operators follow docs/math.md's conventions: ``grad`` appends an axis of 3 (for a vector field
the rows are the components, (grad u)_ij = d u_i / d x_j), ``div`` contracts the last axis,
``laplacian`` is div grad componentwise, ``hessian`` is grad grad, ``sym_grad`` is
(grad u + grad u^T) / 2, ``curl`` is the curl of a vector field, and ``T`` the transpose of a matrix
field.  Fields combine with +, -, * (by numbers, scalar fields, or fields of the same shape
elementwise), / (by numbers or scalar fields), :meth:`Exact.dot` (``sigma.dot(n)`` the traction,
``u.dot(v)``), and ``trace``.  ``Exact.identity()`` is the 3 x 3 identity, so the stress of linear
elasticity is ``2 * mu * u.sym_grad + lam * u.div * Exact.identity()``.

A scalar field is also a level set: :meth:`Exact.level_set` gives a
:class:`~cutfem.geometry.levelset.FunctionLevelSet` with the exact gradient and Hessian, and
``phi.normal`` is grad phi / |grad phi|.

Strings are parsed by sympy (``sympy.sympify``), which evaluates Python: give only expressions you
trust (a script's own text, not input from elsewhere; the command line's ``--surface`` uses its own
safe parser).  Symbols other than x, y, z must be given numbers as keywords
(``Exact("a*x", a=2.0)``); a symbol left free is refused, naming it.
"""

from __future__ import annotations

import numbers

import numpy as np
import sympy

__all__ = ["Exact"]

X = sympy.symbols("x y z", real=True)
_NAMES = {"x": X[0], "y": X[1], "z": X[2], "pi": sympy.pi, "e": sympy.E}


def _sympify(value, constants: dict):
    if isinstance(value, Exact):
        return value.expr
    if isinstance(value, str):
        try:
            expr = sympy.sympify(value, locals={**_NAMES, **{k: sympy.Symbol(k) for k in constants}})
        except (sympy.SympifyError, SyntaxError, TypeError) as exc:
            raise ValueError(f"Exact: cannot read {value!r} as an expression in x, y, z ({exc})") from None
    elif isinstance(value, (list, tuple, np.ndarray, sympy.MatrixBase)):
        items = [_sympify(v, constants) for v in (value.tolist() if isinstance(value, (np.ndarray, sympy.MatrixBase)) else value)]
        return sympy.Array(items)
    else:
        try:
            expr = sympy.sympify(value)
        except sympy.SympifyError:
            raise TypeError(f"Exact: {type(value).__name__} is not an expression; give a sympy expression, a string "
                            "in x, y, z or a number, or a list of them for a vector or matrix field") from None
    if isinstance(expr, (sympy.Array, sympy.MatrixBase)):
        return sympy.Array(expr.tolist())
    return expr


class Exact:
    """A scalar, vector or 3 x 3 matrix field given by sympy expressions in x, y, z (see the module
    docstring).  ``expr``: an expression, a string, a number, or a list (of lists) of them for a
    vector (3,) or a matrix (3, 3) field; ``constants``: numbers for the other symbols."""

    def __init__(self, expr, **constants):
        for name, value in constants.items():
            if not isinstance(value, numbers.Real) or not np.isfinite(value):
                raise ValueError(f"Exact: the constant {name}={value!r} must be a finite real number")
        expr = _sympify(expr, constants)
        subs = {sympy.Symbol(k): v for k, v in constants.items()}
        subs.update({sympy.Symbol(k, real=True): v for k, v in constants.items()})
        if subs:
            expr = expr.subs(subs)
        # the coordinates the caller wrote as plain symbols (sympy.symbols("x")) are ours
        plain = {sympy.Symbol(n): s for n, s in zip("xyz", X)}
        expr = expr.xreplace(plain)
        shape = tuple(expr.shape) if isinstance(expr, sympy.Array) else ()
        if shape not in ((), (3,), (3, 3)):
            raise ValueError(f"Exact: a field is a scalar, a vector of 3 or a 3 x 3 matrix, not of shape {shape}")
        free = sorted(str(s) for s in expr.free_symbols if s not in X)
        if free:
            raise ValueError(f"Exact: the symbol(s) {', '.join(free)} have no value; give numbers as keywords, e.g. "
                             f"Exact(..., {free[0]}=1.0), or write the expression in x, y, z only")
        self.expr = expr
        self.shape = shape
        self._function = None

    # ------------------------------------------------------------------ evaluation
    def __call__(self, x) -> np.ndarray:
        """The field at points ``x`` of shape (..., 3): an array (..., *shape) of floats."""
        x = np.asarray(x, dtype=float)
        if x.ndim == 0 or x.shape[-1] != 3:
            raise ValueError(f"Exact: points must have shape (..., 3), not {x.shape}")
        if self._function is None:
            entries = [self.expr] if not self.shape else list(sympy.flatten(self.expr))
            self._function = sympy.lambdify(X, entries, modules="numpy", cse=True)
        values = self._function(x[..., 0], x[..., 1], x[..., 2])
        lead = x.shape[:-1]
        out = np.empty(lead + (len(values),))
        for k, v in enumerate(values):
            out[..., k] = v  # a constant entry comes back as a number: broadcast
        return out.reshape(lead + self.shape)

    def __repr__(self):
        return f"Exact({self.expr})"

    # ------------------------------------------------------------------ calculus
    @property
    def grad(self) -> "Exact":
        """The gradient: shape + (3,), (grad u)_ij = d u_i / d x_j for a vector field."""
        if self.shape == (3, 3):
            raise ValueError("Exact.grad: the gradient of a matrix field (a third-order tensor) is not a field here")
        return Exact(sympy.derive_by_array(self.expr, X) if not self.shape else
                     sympy.Array([[sympy.diff(c, v) for v in X] for c in self.expr]))

    @property
    def hessian(self) -> "Exact":
        """The Hessian of a scalar field, (3, 3)."""
        self._require((), "hessian")
        return self.grad.grad

    @property
    def div(self) -> "Exact":
        """The divergence: of a vector field a scalar, of a matrix field the vector of its rows' divergences."""
        if self.shape == (3,):
            return Exact(sum(sympy.diff(self.expr[i], X[i]) for i in range(3)))
        if self.shape == (3, 3):
            return Exact([sum(sympy.diff(self.expr[i, j], X[j]) for j in range(3)) for i in range(3)])
        raise ValueError("Exact.div: a scalar field has no divergence; take its gradient or Laplacian")

    @property
    def laplacian(self) -> "Exact":
        """div grad, componentwise for a vector field."""
        if self.shape == ():
            return Exact(sum(sympy.diff(self.expr, v, 2) for v in X))
        self._require((3,), "laplacian")
        return Exact([sum(sympy.diff(c, v, 2) for v in X) for c in self.expr])

    @property
    def sym_grad(self) -> "Exact":
        """eps(u) = (grad u + grad u^T) / 2 of a vector field."""
        self._require((3,), "sym_grad")
        return (self.grad + self.grad.T) / 2

    @property
    def curl(self) -> "Exact":
        """The curl of a vector field."""
        self._require((3,), "curl")
        u, (x, y, z) = self.expr, X
        return Exact([sympy.diff(u[2], y) - sympy.diff(u[1], z), sympy.diff(u[0], z) - sympy.diff(u[2], x),
                      sympy.diff(u[1], x) - sympy.diff(u[0], y)])

    @property
    def T(self) -> "Exact":
        """The transpose of a matrix field."""
        self._require((3, 3), "T")
        return Exact(sympy.permutedims(self.expr, (1, 0)))

    @property
    def trace(self) -> "Exact":
        """The trace of a matrix field."""
        self._require((3, 3), "trace")
        return Exact(sum(self.expr[i, i] for i in range(3)))

    @property
    def norm(self) -> "Exact":
        """The Euclidean (Frobenius) norm, a scalar field."""
        entries = [self.expr] if not self.shape else list(sympy.flatten(self.expr))
        return Exact(sympy.sqrt(sum(e**2 for e in entries)))

    @property
    def normal(self) -> "Exact":
        """grad phi / |grad phi| of a scalar field (the unit normal of its level sets)."""
        self._require((), "normal")
        g = self.grad
        return g / g.norm

    @staticmethod
    def identity() -> "Exact":
        """The 3 x 3 identity matrix field."""
        return Exact(sympy.Array(sympy.eye(3).tolist()))

    def simplify(self) -> "Exact":
        """The same field with sympy's simplification of each entry (faster to evaluate, slower to make)."""
        return Exact(self.expr.applyfunc(sympy.simplify) if self.shape else sympy.simplify(self.expr))

    def level_set(self, **options):
        """This scalar field as a level set {phi < 0} with its exact gradient and Hessian
        (:class:`~cutfem.geometry.levelset.FunctionLevelSet`; ``options`` go to it: ``lipschitz``,
        ``is_distance``, ``area``, ``volume``, ``bounds``, ``name``)."""
        self._require((), "level_set")
        from ..geometry.levelset import FunctionLevelSet

        return FunctionLevelSet(self, gradient=self.grad, hessian=self.hessian, **options)

    def _require(self, shape, what):
        if self.shape != shape:
            kind = {(): "scalar", (3,): "vector", (3, 3): "matrix"}
            raise ValueError(f"Exact.{what}: defined for a {kind[shape]} field, not for a {kind[self.shape]} one")

    # ------------------------------------------------------------------ arithmetic
    def _other(self, other, op):
        if isinstance(other, Exact):
            return other
        if isinstance(other, numbers.Real):
            if not np.isfinite(other):
                raise ValueError(f"Exact: {op} by {other!r}, not a finite number")
            return Exact(other)
        if isinstance(other, (str, sympy.Basic)):
            return Exact(other)
        return NotImplemented

    def _combine(self, other, op, f):
        other = self._other(other, op)
        if other is NotImplemented:
            return other
        a, b = self.expr, other.expr
        if self.shape == other.shape:
            if self.shape:
                return Exact(sympy.Array([f(p, q) for p, q in zip(sympy.flatten(a), sympy.flatten(b))]).reshape(*self.shape))
            return Exact(f(a, b))
        if op in ("*", "/") and other.shape == ():
            return Exact(a.applyfunc(lambda e: f(e, b)))
        if op == "*" and self.shape == ():
            return Exact(b.applyfunc(lambda e: f(a, e)))
        raise ValueError(f"Exact: cannot {op} fields of shapes {self.shape} and {other.shape} (use dot for products "
                         "of vectors and matrices)")

    def __add__(self, other):
        return self._combine(other, "+", lambda p, q: p + q)

    def __radd__(self, other):
        return self._combine(other, "+", lambda p, q: q + p)

    def __sub__(self, other):
        return self._combine(other, "-", lambda p, q: p - q)

    def __rsub__(self, other):
        return self._combine(other, "-", lambda p, q: q - p)

    def __mul__(self, other):
        return self._combine(other, "*", lambda p, q: p * q)

    def __rmul__(self, other):
        return self._combine(other, "*", lambda p, q: q * p)

    def __truediv__(self, other):
        other = self._other(other, "/")
        if other is NotImplemented:
            return other
        if other.shape != ():
            raise ValueError(f"Exact: division by a field of shape {other.shape}; divide by numbers or scalar fields")
        return self._combine(other, "/", lambda p, q: p / q)

    def __neg__(self):
        return self * -1

    def dot(self, other) -> "Exact":
        """The contraction of this field's last axis with the first of ``other``: u . v of vectors,
        sigma n of a matrix and a vector (the traction), A B of matrices."""
        other = self._other(other, "dot")
        if other is NotImplemented or not self.shape or not other.shape:
            raise ValueError("Exact.dot: both fields must be vectors or matrices; multiply by a scalar field with *")
        k = len(self.shape)
        return Exact(sympy.tensorcontraction(sympy.tensorproduct(self.expr, other.expr), (k - 1, k)))

    def __pow__(self, power):
        self._require((), "__pow__")
        return Exact(self.expr ** power)

