"""Generated surface meshes: the torus families of docs/math.md §6.1 and the icosahedral sphere.

:func:`torus_mesh` triangulates an n x n/2 grid in the angles, every node on the torus, in the four
families of the paper (structured, flipped diagonals, perturbed nodes, both); :func:`sphere_mesh`
refines the icosahedron and pushes the new nodes onto the sphere.  Both check their memory before
allocating and return a validated :class:`~cutfem.geometry.surface.SurfaceMesh`.
"""

from __future__ import annotations

import numpy as np

from .surface import SurfaceMesh, check_length
from .surface_checks import _halfedge_table

__all__ = ["torus_mesh", "sphere_mesh", "TORUS_FAMILIES", "RANDOM_FAMILIES", "BYTES_PER_GENERATED_NODE", "SPHERE_MAX_LEVEL"]

#: the torus families drawn at random (their ``seed`` matters)
RANDOM_FAMILIES = ("flipped", "perturbed", "perturbed-flipped")
#: The torus families of docs/math.md §6.1 accepted by :func:`torus_mesh`.
TORUS_FAMILIES = ("structured", *RANDOM_FAMILIES)

#: Peak bytes per node of a generated mesh (:func:`torus_mesh`, :func:`sphere_mesh`, with its
#: validation), checked before allocating: measured 582 (torus, n = 1200) and 656 (sphere, level 9)
#: as the peak resident memory of a fresh process over its baseline, rounded up.
BYTES_PER_GENERATED_NODE = 800

#: The finest level of :func:`sphere_mesh` (20 * 4**10 = 20,971,520 triangles).
SPHERE_MAX_LEVEL = 10


# ---------------------------------------------------------------------------------------------
# generators
# ---------------------------------------------------------------------------------------------


def _int_text(value) -> str:
    """An integer for a message: in full up to 18 digits, else in floating notation (str() of an
    integer beyond 4300 digits raises, and writing out a huge one is slow and unreadable)."""
    value = int(value)
    if abs(value) < 10**18:
        return str(value)
    try:
        return f"{float(value):.3g}"
    except OverflowError:
        return f"{'-' if value < 0 else ''}2**{abs(value).bit_length() - 1} or more"


def _check_int(name: str, value, minimum: int, maximum: int | None = None, why: str = "") -> int:
    """``value`` as an int in [minimum, maximum]; ValueError otherwise (``why`` explains the maximum).
    The bounds are compared before anything is computed from ``value``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}.")
    if value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}; got {_int_text(value)}.")
    if maximum is not None and value > maximum:
        raise ValueError(f"{name} must be an integer <= {maximum}; got {_int_text(value)}{why}.")
    return int(value)


def _available_bytes() -> int:
    from ..memory import available_memory

    return available_memory()[0]


def _check_generated_memory(nodes: int, what: str, fix: str) -> None:
    """Refuse a generated mesh of ``nodes`` nodes whose peak memory (:data:`BYTES_PER_GENERATED_NODE`
    per node) exceeds the memory available (:func:`cutfem.memory.check_memory`), before allocating."""
    from ..memory import check_memory

    try:
        estimate = BYTES_PER_GENERATED_NODE * float(nodes)
    except OverflowError:  # more than 1e308 nodes
        estimate = float("inf")
    check_memory(estimate, what, fix)


def torus_mesh(n: int, family: str = "structured", R: float = 1.0, r: float = 0.5, seed=0) -> SurfaceMesh:
    """Triangulated torus on an n x n/2 grid in the angles (t, p) (docs/math.md §6.1).

    Node (i, j), i = 0..n-1, j = 0..m-1 with m = n // 2, has grid angles t_i = 2 pi i / n,
    p_j = 2 pi j / m and sits at

        x = (R + r cos p) cos t,  y = (R + r cos p) sin t,  z = r sin p,

    so every node lies exactly on the torus rho = sqrt(z^2 + (sqrt(x^2 + y^2) - R)^2) - r = 0.
    Node index i * m + j.  N = n m nodes, 2 N triangles, 3 N edges, Euler characteristic 0.
    Cell (i, j) has corners v00 = (i, j), v10 = (i+1, j), v11 = (i+1, j+1), v01 = (i, j+1)
    (indices periodic) and is split along the diagonal v00-v11 into (v00, v10, v11),
    (v00, v11, v01), or along v10-v01 into (v00, v10, v01), (v10, v11, v01); both are outward
    since x_t x x_p points out of the torus.

    Families:

    * ``"structured"``: every cell split along v00-v11;
    * ``"flipped"``: each cell's diagonal chosen by a fair coin;
    * ``"perturbed"``: each node's (t, p) moved by independent uniform offsets in
      [-dt/4, dt/4] x [-dp/4, dp/4] (dt = 2 pi / n, dp = 2 pi / m), then placed on the torus;
      structured diagonals (the paper's "unstructured" family);
    * ``"perturbed-flipped"``: both.

    Randomness: one ``numpy.random.default_rng(seed)`` draws, always in this order and for every
    family, the n m diagonal coins and then the (n m, 2) node offsets; each family uses what it
    needs.  Hence the same seed gives identical meshes, and "perturbed-flipped" has the nodes of
    "perturbed" and the diagonals of "flipped" for the same seed.

    Notes: the cells of the unperturbed grid are planar isosceles trapezoids, so "flipped" has the
    same area (and stiffness matrix) as "structured".  Requires n even and >= 6 (so m >= 3 and the
    grid is a simplicial complex) and 0 < r < R (an embedded ring torus).  Memory: the n m nodes
    at :data:`BYTES_PER_GENERATED_NODE` each are compared with the memory available before
    anything is allocated (:class:`cutfem.memory.InsufficientMemoryError` naming the size and an n
    that fits).  R and r must lie in :data:`~cutfem.geometry.surface.LENGTH_RANGE`, and an r / R so small that the cells are
    slivers (degenerate by :data:`~cutfem.geometry.surface_checks.DEGENERATE_TOLERANCE`) is refused naming r / R.

    Validation: the grid is closed, manifold (six triangles in one fan at every node) and
    outward by construction, for every family (the offsets move nodes by less than half a cell,
    which keeps the signed volume positive), so only what the node positions could break is
    checked: finite, non-degenerate triangles (:meth:`~cutfem.geometry.surface.SurfaceMesh._check_generated`).
    """
    n = _check_int("n", n, 6)
    if n % 2:
        raise ValueError(f"n must be even (the grid is n x n/2); got n = {n}. Use n = {n + 1}.")
    if family not in TORUS_FAMILIES:
        raise ValueError(f"unknown torus family {family!r}; allowed: {', '.join(TORUS_FAMILIES)}.")
    R = check_length("R", R, "torus_mesh")
    r = check_length("r", r, "torus_mesh")
    if not r < R:
        raise ValueError(f"the torus needs 0 < r < R (a ring torus without self-contact); got R = {R}, r = {r}.")
    m = n // 2
    fits = 2 * int(np.sqrt(_available_bytes() / BYTES_PER_GENERATED_NODE) / 2)  # n**2 / 2 nodes fit
    _check_generated_memory(
        n * m, f"torus_mesh(n={_int_text(n)}) ({_int_text(n * m)} nodes, {_int_text(2 * n * m)} triangles)",
        f"use a smaller n (the memory grows like n**2; n = {fits} fits)" if fits >= 6 else "free memory",
    )
    rng = np.random.default_rng(seed)
    coins = rng.random(n * m) < 0.5
    offsets = rng.uniform(-0.25, 0.25, size=(n * m, 2))

    # node (and cell) index i * m + j; the angles of the unperturbed grid need only n + m values
    gi, gj = np.arange(n, dtype=float)[:, None], np.arange(m, dtype=float)[None, :]
    if family in ("perturbed", "perturbed-flipped"):
        gi = gi + offsets[:, 0].reshape(n, m)
        gj = gj + offsets[:, 1].reshape(n, m)
    t = 2.0 * np.pi * gi / n
    p = 2.0 * np.pi * gj / m
    ring = R + r * np.cos(p)
    points = np.empty((n, m, 3))
    points[..., 0] = ring * np.cos(t)
    points[..., 1] = ring * np.sin(t)
    points[..., 2] = r * np.sin(p)

    v00 = np.arange(n * m).reshape(n, m)
    v10, v01 = np.roll(v00, -1, axis=0), np.roll(v00, -1, axis=1)
    v11 = np.roll(v10, -1, axis=1)
    triangles = np.empty((n, m, 2, 3), dtype=np.int64)
    for k, v in enumerate((v00, v10, v11)):  # main diagonal: (v00, v10, v11), (v00, v11, v01)
        triangles[:, :, 0, k] = v
    for k, v in enumerate((v00, v11, v01)):
        triangles[:, :, 1, k] = v
    if family in ("flipped", "perturbed-flipped"):  # the other diagonal: (v00, v10, v01), (v10, v11, v01)
        flip = coins.reshape(n, m)
        triangles[flip, 0, 2] = v01[flip]
        triangles[flip, 1] = np.stack([v10[flip], v11[flip], v01[flip]], axis=1)
    points, triangles = points.reshape(-1, 3), triangles.reshape(-1, 3)
    mesh = SurfaceMesh(points, triangles, check=False)
    try:
        mesh._check_generated()  # the grid is a closed, outward torus; only the geometry is checked
    except ValueError as err:  # r / R so small that the cells are slivers
        raise ValueError(
            f"torus_mesh(n={n}, R={R:g}, r={r:g}) makes degenerate triangles: the ratio r / R = {r / R:.3g} is too "
            f"small for the grid (cells about {2 * np.pi * R / n:.3g} by {2 * np.pi * r / m:.3g}, slivers by the test of "
            "DEGENERATE_TOLERANCE); use a larger r / R."
        ) from err
    mesh.grid = (n, m)
    return mesh


def _refine_midpoints(points: np.ndarray, triangles: np.ndarray):
    """Split every triangle into four through its edge midpoints (orientation preserved).

    New node N + e at the midpoint of edge e; (v0, v1, v2) with midpoints m0 = (v0 v1),
    m1 = (v1 v2), m2 = (v2 v0) becomes (v0, m0, m2), (m0, v1, m1), (m2, m1, v2), (m0, m1, m2).
    """
    edges, halfedge_edge, _, _ = _halfedge_table(triangles, len(points))
    mid = len(points) + halfedge_edge.reshape(-1, 3)
    new_points = np.concatenate([points, 0.5 * (points[edges[:, 0]] + points[edges[:, 1]])])
    v0, v1, v2 = triangles.T
    m0, m1, m2 = mid.T
    children = np.stack(
        [
            np.stack([v0, m0, m2], 1),
            np.stack([m0, v1, m1], 1),
            np.stack([m2, m1, v2], 1),
            np.stack([m0, m1, m2], 1),
        ],
        axis=1,
    )
    return new_points, children.reshape(-1, 3)


def sphere_mesh(level: int = 3, radius: float = 1.0, center=(0.0, 0.0, 0.0)) -> SurfaceMesh:
    """Icosahedral sphere: the regular icosahedron refined ``level`` times, nodes on the sphere.

    The 12 icosahedron vertices are the cyclic permutations of (0, +-1, +-phi), phi = (1 + sqrt 5)/2,
    scaled to the unit sphere; its 20 faces are the convex hull, oriented outward.  Each refinement
    splits every triangle into four through its edge midpoints and pushes the new nodes radially
    onto the unit sphere; finally x = center + radius * u.  Hence every node satisfies
    |x - center| = radius up to round-off, and

        N = 10 * 4^level + 2,  E = 30 * 4^level,  M = 20 * 4^level,  Euler characteristic 2.

    The area tends to 4 pi radius^2 and the volume to 4/3 pi radius^3 at O(h^2).

    ``radius`` must lie in :data:`~cutfem.geometry.surface.LENGTH_RANGE`.  ``level`` must be an integer in
    0..:data:`SPHERE_MAX_LEVEL`, checked before anything is
    computed from it (a huge level is refused at once); the nodes at
    :data:`BYTES_PER_GENERATED_NODE` each must fit in the memory available
    (:class:`cutfem.memory.InsufficientMemoryError` naming a level that fits).
    """
    from scipy.spatial import ConvexHull

    level = _check_int(
        "level", level, 0, SPHERE_MAX_LEVEL,
        f" (level {SPHERE_MAX_LEVEL} has {20 * 4**SPHERE_MAX_LEVEL:,} triangles; each level multiplies them by 4)",
    )
    radius = check_length("radius", radius, "sphere_mesh")
    center = np.asarray(center, dtype=float)
    if center.shape != (3,) or not np.isfinite(center).all():
        raise ValueError(f"center must be 3 finite coordinates; got {center!r}.")
    nodes = 10 * 4**level + 2
    fits = [k for k in range(level) if BYTES_PER_GENERATED_NODE * (10 * 4**k + 2) <= _available_bytes()]
    _check_generated_memory(
        nodes, f"sphere_mesh(level={level}) ({nodes:,} nodes, {20 * 4**level:,} triangles)",
        f"use a smaller level (the memory grows 4 times a level; level {fits[-1]} fits)" if fits else "free memory",
    )
    phi = 0.5 * (1.0 + np.sqrt(5.0))
    base = np.array([[0.0, s1, s2 * phi] for s1 in (-1.0, 1.0) for s2 in (-1.0, 1.0)])
    verts = np.concatenate([np.roll(base, shift, axis=1) for shift in range(3)])
    verts /= np.linalg.norm(verts, axis=1)[:, None]
    tri = ConvexHull(verts).simplices.astype(np.int64)
    normal = np.cross(verts[tri[:, 1]] - verts[tri[:, 0]], verts[tri[:, 2]] - verts[tri[:, 0]])
    inward = np.einsum("ij,ij->i", normal, verts[tri].sum(axis=1)) < 0
    tri[inward] = tri[inward][:, [0, 2, 1]]
    for _ in range(level):
        verts, tri = _refine_midpoints(verts, tri)
        verts /= np.linalg.norm(verts, axis=1)[:, None]
    return SurfaceMesh(center + radius * verts, tri)
