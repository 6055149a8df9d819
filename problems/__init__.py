"""The problems hosted by cutfem, each registered by name on import (see ``cutfem list``).

* ``mean-curvature-meshed`` / ``mean-curvature-cut``: the stabilized mean curvature vector on
  triangulated surfaces and on cut surfaces (docs/math.md §3).
* ``laplace-beltrami-meshed`` / ``laplace-beltrami-cut``: -Lap_S u + u = f with manufactured
  solutions (docs/math.md §4).
* ``poisson-cut``: fictitious-domain Poisson, Nitsche and ghost penalty (§8).
* ``poisson-csg-cut``: Poisson on a domain of several level sets (a ball cut by a plane), Dirichlet
  on some parts of its boundary and Neumann on others (§16).
* ``interface-poisson-cut``: a coefficient jump across a sphere, Nitsche-XFEM (§9).
* ``bulk-surface-cut``: coupled bulk-surface diffusion (§10).
* ``heat-surface-cut``: the heat equation on a cut sphere, theta-scheme (§11).
* ``heat-moving-cut``: the heat equation in a moving ball, Eulerian BDF1/BDF2 (§13).
* ``elasticity-cut``: compressible linear elasticity in a cut domain, one vector field (§14).
* ``stokes-cut``: Stokes flow in a cut domain, P1-P1, MINRES with a block preconditioner (§14).
* ``two-phase-stokes-cut``: the static bubble, two-phase Stokes with surface tension from the discrete
  mean curvature vector or Laplace-Beltrami (§15).
"""

from . import (bulk_surface, elasticity, heat_moving, heat_surface, interface_poisson, laplace_beltrami, mean_curvature, poisson,
               poisson_csg, stokes, two_phase_stokes)

#: the problem modules, each registering its problems on import
__all__ = ["bulk_surface", "elasticity", "heat_moving", "heat_surface", "interface_poisson", "laplace_beltrami", "mean_curvature",
           "poisson", "poisson_csg", "stokes", "two_phase_stokes"]
