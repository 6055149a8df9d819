"""The problems hosted by cutfem, each registered by name on import (see ``cutfem list``).

* ``mean-curvature-meshed`` / ``mean-curvature-cut``: the stabilized mean curvature vector on
  triangulated surfaces and on cut surfaces (SPEC §3).
* ``laplace-beltrami-meshed`` / ``laplace-beltrami-cut``: -Lap_S u + u = f with manufactured
  solutions (SPEC §4).
"""

from . import bulk_surface, heat_surface, interface_poisson, laplace_beltrami, mean_curvature, poisson  # noqa: F401  (registration on import)
