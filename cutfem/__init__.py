"""cutfem: unfitted (cut) finite element methods on surfaces and in volumes.

The data flow is a chain of plain value objects holding numpy arrays::

    background mesh -> level set -> cut -> quadrature -> P1 space -> forms -> assemble -> solve -> errors

(a triangulated surface skips the level set and the cut).  See README.md for a tour.
"""

__version__ = "0.1.0"

from . import memory as _memory  # noqa: E402

_memory.configure()  # allocation settings for large arrays: see cutfem.memory (CUTFEM_ALLOCATOR=system to opt out)

from .registry import Param, Problem, available_problems, get_problem, register, run  # noqa: E402

__all__ = ["Param", "Problem", "register", "run", "get_problem", "available_problems", "__version__"]
