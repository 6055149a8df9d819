"""Randomized degenerate placements and bad inputs (issue 45): 2,000 and more cases, none of which may
give a silent wrong answer or an error other than the project's clear ones.

Placements: planes and spheres through nodes, edge midpoints, face centres and cell centres of a
structured box, with and without a (true, generous) Lipschitz bound, each cut checked against
exact invariants: S_h closed, |dx(NEG)| + |dx(POS)| = |box| to round-off, the area and the enclosed
volume within the P1 geometry error of the exact ones.  Bad inputs: non-finite, wrongly shaped and
non-numeric level-set values, bad Lipschitz bounds and box sizes, each refused with ValueError (or
its subclasses) and a message that names the input."""

import math

import numpy as np
import pytest

from cutfem.geometry.cut import NEG, POS, cut_mesh
from cutfem.geometry.nodal_values import CutError
from cutfem.geometry.levelset import FunctionLevelSet
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.box import structured_box

pytestmark = pytest.mark.slow

H = 0.25
BOX = structured_box([-1.25] * 3, [1.25] * 3, spacing=H)
BOX_VOLUME = 2.5 ** 3
ONE = lambda x: np.ones(x.shape[:-1])  # noqa: E731


def _special_points(rng, n):
    """Nodes, edge midpoints, face centres and cell centres of the box's lattice near the origin,
    and points a multiple of 1e-15 away from them."""
    base = rng.integers(-2, 3, size=(n, 3)) * H
    shift = rng.integers(0, 2, size=(n, 3)) * (H / 2)
    eps = rng.choice([0.0, 0.0, 1e-15, -1e-15, 1e-9], size=(n, 1))
    return base + shift + eps


def _check_cut(cut, area, volume, radius, what):
    """Closed, the sides fill the box, and the area and volume within 0.8 (h/r)^2 of the exact ones
    (the P1 geometry error of a sphere of radius r: measured up to 0.5 (h/r)^2 at r/h = 2.2-4.8)."""
    assert cut.is_closed, f"{what}: S_h is not closed"
    neg = cut.dx(NEG).integrate(ONE)
    pos = cut.dx(POS).integrate(ONE)
    assert abs(neg + pos - BOX_VOLUME) < 1e-10 * BOX_VOLUME, f"{what}: |NEG| + |POS| = {neg + pos}"
    tol = 0.8 * (H / radius) ** 2
    assert abs(cut.area - area) < tol * area, f"{what}: area {cut.area} against {area}"
    assert abs(neg - volume) < tol * volume, f"{what}: volume {neg} against {volume}"
    return cut.area, neg


def test_spheres_through_lattice_points():
    """1,000 spheres whose centre is a lattice point (or within 1e-15 of one) and whose radius
    reaches another lattice point exactly; with a true but generous Lipschitz bound the cut is the
    same as without one (the bound may only skip cells, never move S_h)."""
    rng = np.random.default_rng(45)
    centres = _special_points(rng, 1000) * 0.4
    through = _special_points(rng, 1000)
    radius = np.linalg.norm(through - centres, axis=1)
    done = 0
    for c, r, bound in zip(centres, radius, rng.choice([None, 1.0, 1e3, 1e10], size=1000)):
        if not 0.55 < r < 1.2 - np.abs(c).max():
            continue  # keep the sphere resolved and inside the box
        phi = lambda x, c=c, r=r: np.linalg.norm(x - c, axis=-1) - r  # noqa: E731
        what = f"sphere c={c.tolist()} r={r!r} L={bound}"
        free = _check_cut(cut_mesh(BOX, FunctionLevelSet(phi)), 4 * math.pi * r * r, 4 / 3 * math.pi * r ** 3, r, what)
        if bound is not None:
            bounded = _check_cut(cut_mesh(BOX, FunctionLevelSet(phi, lipschitz=bound)), 4 * math.pi * r * r, 4 / 3 * math.pi * r ** 3, r, what)
            assert np.allclose(bounded, free, rtol=1e-12, atol=0), f"{what}: {bounded} against {free} without the bound"
        done += 1
    assert done >= 500


def test_planes_through_lattice_points():
    """1,000 planes through lattice points with normals along axes, face diagonals, space diagonals
    and random directions: the two sides fill the box to round-off, and S_h is a section of it."""
    rng = np.random.default_rng(46)
    kinds = [np.eye(3), np.array([[1, 1, 0], [1, 0, 1], [0, 1, 1], [1, -1, 0]]) / math.sqrt(2),
             np.array([[1, 1, 1], [1, -1, 1]]) / math.sqrt(3)]
    points = _special_points(rng, 1000) * 0.5
    done = 0
    for i, p in enumerate(points):
        kind = i % 4
        n = rng.standard_normal(3) if kind == 3 else kinds[kind][rng.integers(len(kinds[kind]))]
        n = n / np.linalg.norm(n) * rng.choice([-1.0, 1.0])
        d = float(n @ p)
        ls = FunctionLevelSet(lambda x, n=n, d=d: x @ n - d, lipschitz=rng.choice([None, 1.0, 1e6]))
        try:
            cut = cut_mesh(BOX, ls, check_boundary=False)
        except CutError as e:
            pytest.fail(f"plane n={n.tolist()} d={d!r}: {e}")
        neg = cut.dx(NEG).integrate(ONE)
        pos = cut.dx(POS).integrate(ONE)
        assert abs(neg + pos - BOX_VOLUME) < 1e-10 * BOX_VOLUME, f"plane n={n.tolist()} d={d!r}: {neg + pos}"
        # the area of S_h is that of the plane's section of the box, positive, at most the largest
        # section (a diagonal plane through the centre: 2.5^2 sqrt 3 for the space diagonal)
        assert 0 < cut.area <= 2.5 * 2.5 * math.sqrt(3) + 1e-9, f"plane n={n.tolist()} d={d!r}: area {cut.area}"
        done += 1
    assert done == 1000


def test_plane_volumes_are_exact():
    """P1 interpolates a plane exactly: |dx(NEG)| equals the exact volume of the clipped box (by the
    formula for an axis-aligned plane) to round-off, also through nodes and faces."""
    rng = np.random.default_rng(47)
    for _ in range(200):
        axis = int(rng.integers(3))
        d = float(rng.integers(-4, 5) * H / 2 + rng.choice([0.0, 1e-15, -1e-15]))
        n = np.zeros(3)
        n[axis] = 1.0
        cut = cut_mesh(BOX, FunctionLevelSet(lambda x, n=n, d=d: x @ n - d), check_boundary=False)
        exact = 2.5 * 2.5 * (d + 1.25)
        assert abs(cut.dx(NEG).integrate(ONE) - exact) < 1e-10, (axis, d)
        assert abs(cut.area - 2.5 * 2.5) < 1e-10, (axis, d)


BAD_VALUES = [
    ("nan everywhere", lambda x: np.full(x.shape[:-1], np.nan)),
    ("nan at one point", lambda x: np.where(np.abs(x[..., 0] - 0.25) < 1e-12, np.nan, np.linalg.norm(x, axis=-1) - 1)),
    ("inf", lambda x: np.where(x[..., 2] > 1.0, np.inf, np.linalg.norm(x, axis=-1) - 1)),
    ("strings", lambda x: np.full(x.shape[:-1], "a")),
    ("objects", lambda x: np.full(x.shape[:-1], None, dtype=object)),
    ("complex", lambda x: np.linalg.norm(x, axis=-1) - 1 + 0j),
    ("an extra axis", lambda x: (np.linalg.norm(x, axis=-1) - 1)[..., None]),
    ("a scalar", lambda x: 1.0),
    ("a list", lambda x: [0.0, 1.0]),
    ("flattened", lambda x: (np.linalg.norm(x, axis=-1) - 1).ravel()[:5]),
    ("positive everywhere", lambda x: np.linalg.norm(x, axis=-1) + 1),
    ("negative everywhere", lambda x: -np.linalg.norm(x, axis=-1) - 1),
    ("a sphere leaving the box", lambda x: np.linalg.norm(x, axis=-1) - 1.5),
]


@pytest.mark.parametrize("what, value", BAD_VALUES, ids=[b[0] for b in BAD_VALUES])
@pytest.mark.parametrize("bound", [None, 1.0])
def test_bad_level_set_values_are_refused(what, value, bound):
    with pytest.raises(ValueError) as info:
        cut_mesh(BOX, FunctionLevelSet(value, lipschitz=bound))
    assert len(str(info.value)) > 20


@pytest.mark.parametrize("bound", [0.0, -1.0, float("nan"), float("inf"), "one", 1j, [1.0]])
def test_bad_lipschitz_bounds_are_refused(bound):
    with pytest.raises((ValueError, TypeError)) as info:
        cut_mesh(BOX, FunctionLevelSet(lambda x: np.linalg.norm(x, axis=-1) - 1, lipschitz=bound))
    assert "lipschitz" in str(info.value).lower()


@pytest.mark.parametrize("lower, upper, kwargs", [
    ([0] * 3, [1] * 3, dict(spacing=0.0)),
    ([0] * 3, [1] * 3, dict(spacing=-0.1)),
    ([0] * 3, [1] * 3, dict(spacing=float("nan"))),
    ([0] * 3, [1] * 3, dict(spacing=float("inf"))),
    ([1] * 3, [0] * 3, dict(spacing=0.1)),
    ([0] * 3, [0] * 3, dict(spacing=0.1)),
    ([0] * 3, [1] * 3, dict(cells=0)),
    ([0] * 3, [1] * 3, dict(cells=-3)),
    ([0] * 3, [1, 1], dict(spacing=0.1)),
    ([0, 0, float("nan")], [1] * 3, dict(spacing=0.1)),
    ([0] * 3, [1] * 3, dict(spacing=1e-300)),
    ([0] * 3, [1] * 3, dict(cells=3_000_000)),
])
def test_bad_boxes_are_refused(lower, upper, kwargs):
    with pytest.raises((ValueError, MemoryError)) as info:
        structured_box(lower, upper, **kwargs)
    assert "-9223372036854775808" not in str(info.value)


def test_random_bad_inputs_never_escape_as_other_errors():
    """1,000 random combinations of a sphere's radius and centre (some leaving the box, some
    missing it, some tiny), a bound and a box spacing: each either cuts into a closed surface whose
    volumes add up, or is refused with ValueError or MemoryError."""
    rng = np.random.default_rng(48)
    ok = refused = 0
    for _ in range(1000):
        r = float(rng.choice([1e-6, 0.05, 0.3, 0.9, 1.3, 5.0]))
        c = rng.uniform(-1.5, 1.5, 3) * rng.choice([0.0, 0.3, 1.0])
        spacing = float(rng.choice([0.25, 0.5, 1.25]))
        box = structured_box([-1.25] * 3, [1.25] * 3, spacing=spacing)
        try:
            cut = cut_mesh(box, Sphere(r, center=c))
        except (ValueError, MemoryError) as e:
            assert len(str(e)) > 20
            refused += 1
            continue
        assert cut.is_closed
        total = cut.dx(NEG).integrate(ONE) + cut.dx(POS).integrate(ONE)
        assert abs(total - BOX_VOLUME) < 1e-10 * BOX_VOLUME
        ok += 1
    assert ok > 100 and refused > 100
