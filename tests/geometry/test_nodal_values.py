"""Tests of cutfem.geometry.nodal_values: the level set at the nodes of a structured box by blocks of
node ids, and the refusal of a wrong number of given nodal values."""

import numpy as np
import pytest

from cutfem.geometry.box import structured_box
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.nodal_values import snapped_nodal_values
from cutfem.geometry.shapes import Sphere, Torus

# a background box with binary-exact nodes (spacing 0.25)
SPHERE_BOX = structured_box([-2.0] * 3, [2.0] * 3, spacing=0.25)


def test_nodal_values_of_a_structured_box_go_by_blocks(monkeypatch):
    """On a structured box the level set is evaluated block by block of node ids, never on the
    box's (N, 3) coordinates: the same values as on those coordinates, and no coordinates kept."""
    import cutfem.geometry.nodal_values as nodal
    from cutfem.geometry.nodal_values import nodal_values

    monkeypatch.setattr(nodal, "NODE_BLOCK", 97)
    box = structured_box([-1.4, -1.4, -0.7], [1.4, 1.4, 0.7], cells=(9, 8, 5))
    torus = Torus(1.0, 0.5)
    values = nodal_values(box, torus)
    assert "points" not in box.__dict__
    np.testing.assert_array_equal(values, torus.value(box.points))
    with pytest.raises(ValueError, match="background nodes"):
        nodal_values(box, lambda x: np.where(x[..., 0] > 1.3, np.nan, 1.0))


def test_nodal_values_of_the_wrong_length():
    values = Sphere(1.0).value(SPHERE_BOX.points)
    with pytest.raises(ValueError, match=f"got {values.size - 1} nodal values for a mesh of {values.size} nodes"):
        cut_mesh(SPHERE_BOX, values[:-1])
    with pytest.raises(ValueError, match="nodal values"):
        snapped_nodal_values(SPHERE_BOX, np.append(values, 1.0))
