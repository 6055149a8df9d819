"""cutfem: unfitted (cut) finite element methods on surfaces and in volumes.

The data flow is a chain of plain value objects holding numpy arrays::

    background mesh -> level set -> cut -> quadrature -> P1 space -> forms -> assemble -> solve -> errors

(a triangulated surface skips the level set and the cut).  ``import cutfem as cf`` gives the names a
research script needs, listed in ``__all__`` (``docs/examples/`` shows them at work)::

    import cutfem as cf
    cut = cf.cut_mesh(cf.structured_box([-1.2] * 3, [1.2] * 3, spacing=0.2), cf.Sphere(1.0))
    V = cf.CutP1Space(cut, cf.NEG)

Everything else is reachable through its module (``cutfem.kernels``, ``cutfem.memory``, ...).

Import laziness lives here and only here: :data:`_NAMES` maps each public name to the module that
defines it, and the module-level ``__getattr__`` (PEP 562) imports that module on the first use of
the name.  So ``import cutfem`` imports no numba, scipy or matplotlib (a CLI start, a forked worker
or ``cutfem --version`` pays only for what it uses), and changes nothing process-wide.  The
``cutfem`` command and the benchmark studies tune how the process allocates large arrays
(:func:`cutfem.memory.configure`); a script that builds large problems may call it too.

One public name is also a module's name: ``solve`` is the function :func:`cutfem.solve.solve`.  The
import system binds a package's submodule as its attribute, which would make ``cutfem.solve`` the
function or the module depending on what was imported before; the package's type keeps it the
function (:class:`_Face`), and the module is ``sys.modules["cutfem.solve"]`` or ``from cutfem.solve
import ...``.
"""

import importlib
import sys
import types

__version__ = "0.1.0"

#: public name -> the module defining it (relative to this package): the one table of the flat face
_NAMES = {
    # backgrounds and surface meshes, and their files
    "structured_box": ".mesh",
    "read_mesh": ".mesh",
    "write_mesh": ".mesh",
    "read_surface": ".surface",
    "write_surface": ".surface",
    "sphere_mesh": ".surface",
    "torus_mesh": ".surface",
    # level sets
    "Sphere": ".levelset",
    "Torus": ".levelset",
    "Ellipsoid": ".levelset",
    "FunctionLevelSet": ".levelset",
    "SignedDistance": ".levelset",
    # the cut and its sides
    "cut_mesh": ".cut",
    "CutMesh": ".cut",
    "NEG": ".markers",
    "POS": ".markers",
    "CUT": ".markers",
    # spaces
    "CutP1Space": ".spaces",
    "SurfaceP1Space": ".spaces",
    "ProductSpace": ".spaces",
    # the form language
    "bilinear_form": ".forms",
    "linear_form": ".forms",
    "dot": ".forms",
    "jump": ".forms",
    "avg": ".forms",
    "ZERO": ".forms",
    "assemble": ".forms",
    "apply_dirichlet": ".forms",
    # the built-in terms
    "mass": ".forms",
    "stiffness": ".forms",
    "tangential_stiffness": ".forms",
    "load": ".forms",
    "position_load": ".forms",
    "basis_integrals": ".forms",
    "nitsche": ".forms",
    "nitsche_load": ".forms",
    "interface_nitsche": ".forms",
    "face_jump_penalty": ".forms",
    "edge_jump_penalty": ".forms",
    "normal_gradient_penalty": ".forms",
    # solvers
    "solve": ".solve",
    "SolverError": ".solve",
    "DirectSolver": ".solve",
    "CGSolver": ".solve",
    "GeometricMultigrid": ".solve",
    # error norms and convergence rates
    "l2_error": ".errors",
    "h1_error": ".errors",
    "l2_h1_errors": ".errors",
    "rates": ".errors",
    "fitted_rate": ".errors",
    # registered problems and runs
    "register": ".registry",
    "Param": ".registry",
    "Problem": ".registry",
    "run": ".registry",
    "available_problems": ".registry",
    "get_problem": ".registry",
}

#: public names that are also the names of submodules (see the module docstring)
_SHADOWED = ("solve",)

__all__ = [*_NAMES, "__version__"]


def _resolve(name):
    return getattr(importlib.import_module(_NAMES[name], __name__), name)


def __getattr__(name):
    """The public ``name`` from its module, imported on first use and then kept in this module's
    namespace; an unknown name raises AttributeError naming it and the closest public name."""
    if name not in _NAMES:
        import difflib

        close = difflib.get_close_matches(name, __all__, n=1)
        hint = f"; did you mean cutfem.{close[0]}?" if close else ""
        raise AttributeError(f"module 'cutfem' has no attribute {name!r}{hint}")
    value = _resolve(name)
    if name not in _SHADOWED:
        globals()[name] = value
    return value


def __dir__():
    return sorted({*globals(), *__all__})


def _shadowed_property(name):
    def get(module):
        return _resolve(name)

    def set_(module, value):
        # the import system binds the submodule here after ``import cutfem.<name>``; the public
        # name stays the function, the module stays in sys.modules
        if not (isinstance(value, types.ModuleType) and value.__name__ == f"{__name__}.{name}"):
            raise AttributeError(f"cutfem.{name} is the public function {name}; it cannot be rebound")

    return property(get, set_)


class _Face(types.ModuleType):
    """The package's type: a module whose names in :data:`_SHADOWED` always give the public object."""

    solve = _shadowed_property("solve")


sys.modules[__name__].__class__ = _Face
