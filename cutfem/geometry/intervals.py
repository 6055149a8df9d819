"""Interval enclosures of a level set over boxes: the band search's local bound.

An :class:`Interval` is a pair of arrays ``lo <= hi`` standing for the sets [lo, hi] elementwise.
Passed to a user's phi in place of the points (x[..., k] gives the interval of coordinate k), the
arithmetic of phi (``+ - * /``, integer powers, ``sqrt exp log abs``, ``minimum maximum``, ``sin
cos``, ``numpy.sum``) is carried out on intervals, each result rounded outward (one ulp for the exactly rounded
operations + - * / sqrt, four ulps for the library functions exp log sin cos), so the result
encloses every value phi takes on the box: if 0 is not in it, phi has no zero in the box.  That is
the natural interval extension (Moore, Interval Analysis, 1966): a rigorous enclosure, and its width
shrinks in proportion to the box, so on small boxes it is close to the true range.  Any operation
not listed raises :class:`NoEnclosure` (a TypeError), and the caller falls back on the global
Lipschitz bound.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Interval", "NoEnclosure", "enclosure"]


class NoEnclosure(TypeError):
    """phi uses an operation that has no interval version here."""


def _down(a, ulps=1):
    for _ in range(ulps):
        a = np.nextafter(a, -np.inf)
    return a


def _up(a, ulps=1):
    for _ in range(ulps):
        a = np.nextafter(a, np.inf)
    return a


def _parts(v):
    if isinstance(v, Interval):
        return v.lo, v.hi
    if isinstance(v, (int, float, np.integer, np.floating)) or (isinstance(v, np.ndarray) and v.dtype.kind in "fiu"):
        a = np.asarray(v, dtype=float)
        return a, a
    raise NoEnclosure(f"no interval version for operands of type {type(v).__name__}")


class Interval:
    """Elementwise intervals [lo, hi] (see the module)."""

    __array_priority__ = 1000

    def __init__(self, lo, hi):
        self.lo = np.asarray(lo, dtype=float)
        self.hi = np.asarray(hi, dtype=float)

    @property
    def shape(self):
        return self.lo.shape

    @property
    def ndim(self):
        return self.lo.ndim

    def __getitem__(self, key):
        return Interval(self.lo[key], self.hi[key])

    def __len__(self):
        return len(self.lo)

    # -- arithmetic -----------------------------------------------------------------------------
    def __add__(self, other):
        (a, b), (c, d) = _parts(self), _parts(other)
        return Interval(_down(a + c), _up(b + d))

    __radd__ = __add__

    def __sub__(self, other):
        (a, b), (c, d) = _parts(self), _parts(other)
        return Interval(_down(a - d), _up(b - c))

    def __rsub__(self, other):
        return Interval(*_parts(other)) - self

    def __neg__(self):
        return Interval(-self.hi, -self.lo)

    def __pos__(self):
        return self

    def __mul__(self, other):
        if other is self:
            return self._square()
        (a, b), (c, d) = _parts(self), _parts(other)
        with np.errstate(invalid="ignore"):
            p = np.stack([a * c, a * d, b * c, b * d])
        p = np.where(np.isnan(p), 0.0, p)  # 0 * inf: the product of a zero and an unbounded end
        return Interval(_down(p.min(axis=0)), _up(p.max(axis=0)))

    __rmul__ = __mul__

    def _square(self):
        a, b = self.lo, self.hi
        lo = np.where((a <= 0) & (b >= 0), 0.0, np.minimum(a * a, b * b))
        return Interval(_down(lo), _up(np.maximum(a * a, b * b)))

    def __truediv__(self, other):
        c, d = _parts(other)
        if np.any((c <= 0) & (d >= 0)):
            raise NoEnclosure("division by an interval that contains 0")
        return self * Interval(_down(1.0 / d), _up(1.0 / c))

    def __rtruediv__(self, other):
        return Interval(*_parts(other)) / self

    def __pow__(self, n):
        if isinstance(n, (int, np.integer)) or (isinstance(n, (float, np.floating)) and float(n).is_integer()):
            n = int(n)
            if n == 0:
                return Interval(np.ones_like(self.lo), np.ones_like(self.hi))
            if n < 0:
                return 1.0 / (self ** (-n))
            result, base = None, self
            while n:
                if n & 1:
                    result = base if result is None else result * base
                n >>= 1
                if n:
                    base = base._square()
            return result
        if isinstance(n, (float, np.floating)) and n == 0.5:
            return _sqrt(self)
        raise NoEnclosure(f"no interval version of a power {n!r}")

    # -- numpy functions -------------------------------------------------------------------------
    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        if method != "__call__" or kwargs:
            raise NoEnclosure(f"no interval version of numpy.{ufunc.__name__}.{method}")
        if ufunc in _BINARY:
            a, b = inputs
            a = a if isinstance(a, Interval) else Interval(*_parts(a))
            return _BINARY[ufunc](a, b)
        if ufunc in _UNARY:
            return _UNARY[ufunc](inputs[0])
        raise NoEnclosure(f"no interval version of numpy.{ufunc.__name__}")

    def __array_function__(self, func, types, args, kwargs):
        if func is np.sum and len(args) == 1 and set(kwargs) <= {"axis"}:
            return self._sum(kwargs.get("axis"))
        raise NoEnclosure(f"no interval version of numpy.{func.__name__}")

    def _sum(self, axis):
        """The sum along ``axis``, widened by 2 n eps times the sum of the ends' magnitudes (n terms):
        more than the rounding of any order of summation."""
        lo, hi = self.lo.sum(axis=axis), self.hi.sum(axis=axis)
        n = self.lo.size // max(lo.size, 1)
        slack = 2.0 * n * np.finfo(float).eps * np.maximum(np.abs(self.lo).sum(axis=axis), np.abs(self.hi).sum(axis=axis))
        return Interval(_down(lo - slack), _up(hi + slack))

    def __bool__(self):
        raise NoEnclosure("an interval has no truth value (phi branches on its argument)")


def _sqrt(a):
    """sqrt over [max(lo, 0), hi]: it encloses every real value of sqrt on the interval (a negative
    lower end is mostly the outward rounding of a sum of squares; where the argument really is
    negative phi is NaN, no zero of phi is there, and the evaluated points report the NaN)."""
    if np.any(a.hi < 0):
        raise NoEnclosure("sqrt of an interval of negative values")
    return Interval(_down(np.sqrt(np.maximum(a.lo, 0.0))), _up(np.sqrt(a.hi)))


def _monotone(fn, ulps=4, domain=None):
    def apply(a):
        if domain is not None and np.any(a.lo <= domain):
            raise NoEnclosure(f"{fn.__name__} of an interval outside its domain")
        with np.errstate(over="ignore"):
            return Interval(_down(fn(a.lo), ulps), _up(fn(a.hi), ulps))
    return apply


def _abs(a):
    lo = np.where(a.lo >= 0, a.lo, np.where(a.hi <= 0, -a.hi, 0.0))
    return Interval(lo, np.maximum(np.abs(a.lo), np.abs(a.hi)))


def _cos(a):
    """cos over [lo, hi]: the ends' values, and +-1 where a multiple of pi lies inside.  The
    interval is first widened by 1e-9 (1 + |end|), far more than the rounding of the multiples of
    pi compared with it (a wider argument only widens the enclosure)."""
    lo_x = a.lo - 1e-9 * (1.0 + np.abs(a.lo))
    hi_x = a.hi + 1e-9 * (1.0 + np.abs(a.hi))
    ends = np.stack([np.cos(lo_x), np.cos(hi_x)])
    has_max = 2 * np.pi * np.floor(hi_x / (2 * np.pi)) >= lo_x  # some 2 k pi inside
    has_min = 2 * np.pi * np.floor((hi_x - np.pi) / (2 * np.pi)) + np.pi >= lo_x  # some (2 k + 1) pi inside
    hi = np.where(has_max, 1.0, np.minimum(_up(ends.max(axis=0), 4), 1.0))
    lo = np.where(has_min, -1.0, np.maximum(_down(ends.min(axis=0), 4), -1.0))
    return Interval(lo, hi)


def _sin(a):
    return _cos(a - np.pi / 2)


def _minimum(a, b):
    b = b if isinstance(b, Interval) else Interval(*_parts(b))
    return Interval(np.minimum(a.lo, b.lo), np.minimum(a.hi, b.hi))


def _maximum(a, b):
    b = b if isinstance(b, Interval) else Interval(*_parts(b))
    return Interval(np.maximum(a.lo, b.lo), np.maximum(a.hi, b.hi))


_BINARY = {
    np.add: lambda a, b: a + b,
    np.subtract: lambda a, b: a - b,
    np.multiply: lambda a, b: a * b,
    np.true_divide: lambda a, b: a / b,
    np.power: lambda a, b: a ** (b if not isinstance(b, np.ndarray) or b.ndim else b.item()),
    np.minimum: _minimum,
    np.maximum: _maximum,
}
_UNARY = {
    np.negative: lambda a: -a,
    np.positive: lambda a: a,
    np.square: lambda a: a._square(),
    np.sqrt: _sqrt,
    np.exp: _monotone(np.exp),
    np.log: _monotone(np.log, domain=0.0),
    np.absolute: _abs,
    np.cos: _cos,
    np.sin: _sin,
}


def enclosure(fn, lower, upper):
    """``(lo, hi)`` enclosing fn(x) over each box [lower[i], upper[i]] (k, 3), or None when fn uses
    an operation with no interval version (or fails on intervals, or gives no finite enclosure) or
    returns something else than one interval per box."""
    box = Interval(_down(np.asarray(lower, dtype=float), 2), _up(np.asarray(upper, dtype=float), 2))
    try:
        with np.errstate(all="ignore"):
            out = fn(box)
    except Exception:  # any failure of the user's phi on intervals: no local information
        return None
    if isinstance(out, Interval):
        lo, hi = out.lo, out.hi
    elif isinstance(out, (int, float, np.ndarray)) and np.asarray(out).dtype.kind == "f":
        lo = hi = np.asarray(out, dtype=float)
    else:
        return None
    if lo.shape != (len(box.lo),) or hi.shape != lo.shape:
        return None
    bad = ~(np.isfinite(lo) & np.isfinite(hi))
    lo, hi = np.where(bad, -np.inf, lo), np.where(bad, np.inf, hi)
    return lo, hi
