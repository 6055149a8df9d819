"""The surface heat equation (docs/math.md §11) at its edges: the steps it takes, the inputs it
refuses, and the rates of the schemes in time at a fixed mesh.

Fast: spacing 0.4 and 0.2 (208 and 676 unknowns)."""

import numpy as np
import pytest

import cutfem
from cutfem.registry import ProblemError


def _run(**kw):
    kw.setdefault("levels", [0.4])
    return cutfem.run("heat-surface-cut", **kw).records[0]


@pytest.mark.parametrize("levels, radius", [([1.5], 1.0), ([0.4], 0.05)])
def test_a_spacing_that_does_not_resolve_the_sphere_is_refused(levels, radius):
    """A background cell as large as the sphere gives a surface of the wrong topology (and a node
    at the centre, where the closest point is undefined): refused with the fix, not a NaN load."""
    with pytest.raises(ProblemError, match=r"too coarse to resolve the surface .*use a smaller spacing"):
        _run(levels=levels, radius=radius)
