"""Signed distance to meshes, the generators' size checks and the analytic surfaces at extreme
sizes: each test asserts numbers or the words of the error."""

from __future__ import annotations

import re

import numpy as np
import pytest

from cutfem.memory import InsufficientMemoryError
from cutfem.surface import sphere_mesh, torus_mesh


# ----------------------------------------------------------------------------------------------
# generators: sizes checked before anything is computed or allocated
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("level, shown", [(10**20, "1e+20"), (100000, "100000"), (11, "11")])
def test_sphere_mesh_refuses_a_level_above_the_finest_at_once(level, shown):
    with pytest.raises(ValueError, match=re.escape(f"level must be an integer <= 10; got {shown} (level 10 has 20,971,520")):
        sphere_mesh(level)


@pytest.mark.parametrize("call, message", [
    (lambda: sphere_mesh(-1), "level must be an integer >= 0; got -1."),
    (lambda: sphere_mesh(-10**5000), "level must be an integer >= 0; got -2**16609 or more."),
    (lambda: torus_mesh(4), "n must be an integer >= 6; got 4."),
    (lambda: torus_mesh(-2), "n must be an integer >= 6; got -2."),
])
def test_generators_refuse_small_and_negative_sizes(call, message):
    with pytest.raises(ValueError) as err:
        call()
    assert str(err.value) == message


def test_torus_mesh_checks_its_memory_before_allocating(monkeypatch):
    monkeypatch.setenv("CUTFEM_MEMORY_LIMIT", "100MiB")
    with pytest.raises(InsufficientMemoryError) as err:
        torus_mesh(10**6)
    assert str(err.value).startswith(
        "torus_mesh(n=1000000) (500000000000 nodes, 1000000000000 triangles) needs about 364 TiB of memory, "
        "more than the 100 MiB available (CUTFEM_MEMORY_LIMIT); use a smaller n (the memory grows like n**2; n = 362 fits)"
    )
    assert torus_mesh(362).n_points == 362 * 181  # the size named fits
    with pytest.raises(InsufficientMemoryError, match=r"sphere_mesh\(level=8\) \(655,362 nodes.*level 6 fits"):
        sphere_mesh(8)
