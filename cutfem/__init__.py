"""cutfem: unfitted (cut) finite element methods on surfaces and in volumes.

The data flow is a chain of plain value objects holding numpy arrays::

    background mesh -> level set -> cut -> quadrature -> P1 space -> forms -> assemble -> solve -> errors

(a triangulated surface skips the level set and the cut).  See README.md for a tour.

Importing cutfem changes nothing process-wide.  The ``cutfem`` command and the benchmark studies
tune how the process allocates large arrays (:func:`cutfem.memory.configure`); a script that
builds large problems may call it too.
"""

__version__ = "0.1.0"

from .registry import Param, Problem, available_problems, get_problem, register, run  # noqa: E402

__all__ = ["Param", "Problem", "register", "run", "get_problem", "available_problems", "__version__"]
