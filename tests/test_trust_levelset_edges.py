"""Level sets at the edges (issue 45): the zero rule on the level set's own local scale, mesh files
that cannot resolve what is asked, and the errors of user level sets and of the --surface flag,
through Python and the command line."""

import numpy as np
import pytest

from cutfem.cut import CutError, cut_mesh, snapped_nodal_values
from cutfem.levelset import FunctionLevelSet
from cutfem.mesh import structured_box


def _norm_minus_one(x):
    return np.linalg.norm(x, axis=-1) - 1.0


def _exp_sphere(x):
    return (np.linalg.norm(x, axis=-1) - 1.0) * np.exp(10.0 * x[..., 0])


@pytest.mark.parametrize("f, bound", [(_norm_minus_one, 1e10), (_exp_sphere, 3.95e6)])
def test_a_generous_lipschitz_bound_does_not_move_the_surface(f, bound):
    """A true but generous bound once set the snap tolerance to 1e-12 L diam (0.043 for L = 1e10):
    nodes 0.04 from the unit sphere were zeroed and the area was 15.98 instead of 12.56.  The snap
    is local now: the band search gives the cut of the full evaluation, and only nodes on the
    sphere to round-off are zero."""
    box = structured_box([-1.25] * 3, [1.25] * 3, spacing=0.05)  # the box
    bounded = cut_mesh(box, FunctionLevelSet(f, lipschitz=bound))
    plain = cut_mesh(box, FunctionLevelSet(f))  # every node evaluated, no bound
    assert abs(plain.area - 4 * np.pi) < 0.05 * 4 * np.pi  # the discretization error of this level set
    assert abs(bounded.area - plain.area) < 1e-12 * plain.area
    assert bounded.n_tets == plain.n_tets and bounded.is_closed
    zero = bounded.points[bounded.values == 0]
    assert np.all(np.abs(np.linalg.norm(zero, axis=-1) - 1.0) < 1e-12)
    everywhere = snapped_nodal_values(box, FunctionLevelSet(f, lipschitz=bound))
    x = box.node_coordinates(np.flatnonzero(everywhere == 0))
    assert np.all(np.abs(np.linalg.norm(x, axis=-1) - 1.0) < 1e-12)


def test_generous_bound_snaps_the_nodes_on_a_plane_through_nodes():
    """Degenerate placements stay closed with a generous bound: a plane through a layer of nodes,
    its values zero to rounding (0.1 * k - 0.3 is not 0 in floating point), is snapped there."""
    box = structured_box([-1, -1, -1], [1, 1, 1], spacing=0.1)
    for lipschitz in (None, 1.0, 1e8):
        sphere_ish = FunctionLevelSet(lambda x: np.maximum(np.abs(x[..., 2] - 0.3), np.linalg.norm(x[..., :2], axis=-1) - 0.5) - 0.2,
                                      lipschitz=lipschitz)
        cut = cut_mesh(box, sphere_ish)
        assert cut.is_closed
        z = cut.points[cut.values == 0][:, 2]
        assert z.size and np.all(np.isclose(z, 0.1) | np.isclose(z, 0.5) | (np.abs(np.linalg.norm(cut.points[cut.values == 0][:, :2], axis=-1) - 0.7) < 1e-12))
