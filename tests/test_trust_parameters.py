"""Issue 45, items 2d, 2e and the messages of part 4 that concern forms and parameters: inputs that
gave a wrong number without a word, or a message that named neither the cause nor the fix.

Expected numbers come from the mathematics, never from the code under test: the integral of a
constant c over a measure is c times its size (the sum of the P1 basis integrals is the size,
since the basis functions sum to one); the penalty ranges are those stated in the docstrings.
"""

import numpy as np
import pytest

from cutfem.cut import cut_mesh
from cutfem.forms import ZERO, assemble, bilinear_form, linear_form, mass
from cutfem.levelset import Sphere
from cutfem.markers import NEG
from cutfem.mesh import structured_box
from cutfem.spaces import CutP1Space


@pytest.fixture(scope="module")
def cut():
    return cut_mesh(structured_box([-1.2] * 3, [1.2] * 3, spacing=0.4), Sphere(0.8))


# --- 2e: w.at(f) must never return the values of another function --------------------------------

def test_w_at_gives_each_inline_function_its_own_values(cut):
    """Functions made inline in a loop are freed after each call, so CPython gives the next one the
    same id: a cache keyed by id(f) returned the first function's values for all of them (3 * size
    instead of (1 + 2 + 3) * size)."""
    dx = cut.dx(NEG)
    V = CutP1Space(cut, NEG)

    @linear_form
    def constants(v, w):
        total = 0.0
        for c in (1.0, 2.0, 3.0):
            total = total + w.at(lambda x, c=c: np.full(x.shape[:-1], c))
        return total * v

    b = assemble(constants * dx, V)
    assert b.sum() == pytest.approx(6.0 * dx.size, rel=1e-12)


def test_w_at_still_evaluates_a_named_function_once_per_block(cut):
    """The cache keyed by the function itself keeps its purpose: one evaluation per block of cells
    for a function defined once, however many basis pairs the integrand is evaluated for."""
    dx = cut.dx(NEG)
    V = CutP1Space(cut, NEG)
    calls = []

    def f(x):
        calls.append(x.shape[0])
        return np.ones(x.shape[:-1])

    @bilinear_form
    def weighted(u, v, w):
        return w.at(f) * u * v

    K = assemble(weighted * dx, V)
    M = assemble(mass(dx), V)
    assert abs(K - M).max() <= 1e-12 * abs(M).max()
    assert len(calls) == len(list(dx.blocks(2)))


# --- part 4: a sum of ZERO terms is ZERO ----------------------------------------------------------

def test_a_sum_of_zero_terms_is_zero_and_couples_nothing(cut):
    """sum() starts from the number 0, and 0 + ZERO was 0: the pair of fields (0, 1) then looked
    coupled and its integrand returned the integer 0, refused for its shape ().  Now the sum is
    ZERO and the matrix is the block-diagonal mass matrix of the two fields."""
    from cutfem.forms import mass
    from cutfem.markers import POS
    from cutfem.spaces import ProductSpace

    assert sum([ZERO, ZERO]) is ZERO
    assert 0 - ZERO is ZERO and ZERO - 0 is ZERO and 0.0 + ZERO is ZERO
    W = ProductSpace(CutP1Space(cut, NEG), CutP1Space(cut, POS))
    ds = cut.ds()

    @bilinear_form(symmetric=True)
    def diagonal(u, v, w):
        return sum(u[k] * v[k] for k in range(2))

    K = assemble(diagonal * ds, W)
    M = assemble(mass(ds, field=0) + mass(ds, field=1), W)
    assert abs(K - M).max() <= 1e-12 * abs(M).max()


def test_an_integrand_returning_one_number_is_told_why(cut):
    V = CutP1Space(cut, NEG)

    @bilinear_form
    def nothing(u, v, w):
        return 0

    with pytest.raises(ValueError, match=r"returned the single number 0, not values at the quadrature points.*ZERO"):
        assemble(nothing * cut.dx(NEG), V)
