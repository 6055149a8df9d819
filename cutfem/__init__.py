"""cutfem: unfitted (cut) finite element methods on surfaces and in volumes.

The data flow is a chain of plain value objects holding numpy arrays::

    background mesh -> level set -> cut -> quadrature -> P1 space -> forms -> assemble -> solve -> errors

(a triangulated surface skips the level set and the cut).  ``import cutfem as cf`` gives the names a
research script needs, listed in ``__all__`` (``docs/examples/`` shows them at work)::

    import cutfem as cf
    cut = cf.cut_mesh(cf.structured_box([-1.2] * 3, [1.2] * 3, spacing=0.2), cf.Sphere(1.0))
    V = cf.CutSpace(cut, cf.NEG)

Everything else is reachable through its subpackage: :mod:`cutfem.geometry` (meshes, level sets,
surfaces, the cut, measures, quadrature), :mod:`cutfem.fem` (spaces, forms and their pointwise values, terms and elasticity, assembly, norms),
:mod:`cutfem.solvers`, :mod:`cutfem.runs` (registry, runner, command line, convergence, plots),
:mod:`cutfem.distributed` (slabs of a box on MPI ranks, the system on PETSc),
:mod:`cutfem.problems`, :mod:`cutfem.studies`, and :mod:`cutfem.memory`.  The compiled kernels
(``*_kernels.py`` beside each stage, and :mod:`cutfem.jit`) are private.

Import laziness lives here and only here: :data:`_NAMES` maps each public name to the module that
defines it, and the module-level ``__getattr__`` (PEP 562) imports that module on the first use of
the name.  So ``import cutfem`` imports no numba, scipy or matplotlib (a CLI start, a forked worker
or ``cutfem --version`` pays only for what it uses), and changes nothing process-wide.  The
``cutfem`` command and the benchmark studies tune how the process allocates large arrays
(:func:`cutfem.memory.configure`); a script that builds large problems may call it too.
"""

import importlib

__version__ = "0.1.0"

#: public name -> the module defining it (relative to this package): the one table of the flat face
_NAMES = {
    # backgrounds and surface meshes, and their files
    "structured_box": ".geometry.box",
    "read_mesh": ".geometry.mesh",
    "write_mesh": ".geometry.mesh",
    "read_surface": ".geometry.surface",
    "write_surface": ".geometry.surface",
    "sphere_mesh": ".geometry.surface_meshes",
    "torus_mesh": ".geometry.surface_meshes",
    # level sets
    "Sphere": ".geometry.shapes",
    "Torus": ".geometry.shapes",
    "Ellipsoid": ".geometry.shapes",
    "Plane": ".geometry.shapes",
    "FunctionLevelSet": ".geometry.levelset",
    "SignedDistance": ".geometry.signed_distance",
    # domains of several level sets
    "intersection": ".geometry.csg",
    "union": ".geometry.csg",
    "difference": ".geometry.csg",
    "complement": ".geometry.csg",
    "Domain": ".geometry.csg",
    # the cut and its sides
    "cut_mesh": ".geometry.cut",
    "CutMesh": ".geometry.cut",
    "CsgCut": ".geometry.csg_cut",
    "NEG": ".geometry.markers",
    "POS": ".geometry.markers",
    "CUT": ".geometry.markers",
    # spaces
    "CutSpace": ".fem.spaces",
    "SurfaceP1Space": ".fem.spaces",
    "VectorSpace": ".fem.spaces",
    "RealSpace": ".fem.spaces",
    "ProductSpace": ".fem.spaces",
    # the form language
    "bilinear_form": ".fem.forms",
    "linear_form": ".fem.forms",
    "assemble": ".fem.forms",
    "dot": ".fem.pointwise",
    "inner": ".fem.pointwise",
    "jump": ".fem.pointwise",
    "avg": ".fem.pointwise",
    "ZERO": ".fem.pointwise",
    # the built-in terms
    "mass": ".fem.terms",
    "stiffness": ".fem.terms",
    "tangential_stiffness": ".fem.terms",
    "load": ".fem.terms",
    "position_load": ".fem.terms",
    "basis_integrals": ".fem.terms",
    "nitsche": ".fem.terms",
    "interface_nitsche": ".fem.terms",
    "face_jump_penalty": ".fem.terms",
    "edge_jump_penalty": ".fem.terms",
    "normal_gradient_penalty": ".fem.terms",
    "apply_dirichlet": ".fem.terms",
    "divergence": ".fem.coupling",
    "mean_constraint": ".fem.coupling",
    "elasticity": ".fem.elasticity",
    "elasticity_nitsche": ".fem.elasticity",
    # solvers
    "solve": ".solvers.solve",
    "SolverError": ".solvers.diagnose",
    "DirectSolver": ".solvers.direct",
    "CGSolver": ".solvers.krylov",
    "GeometricMultigrid": ".solvers.multigrid",
    # moving domains: the extended domain of a time step, its strip width, the transfer of a solution
    "ActiveDomain": ".fem.moving",
    "strip_width": ".fem.moving",
    "transfer": ".fem.moving",
    # exact fields from sympy (manufactured solutions and their data)
    "Exact": ".fem.exact",
    # error norms and convergence rates
    "l2_error": ".fem.norms",
    "h1_error": ".fem.norms",
    "l2_h1_errors": ".fem.norms",
    "rates": ".fem.norms",
    "fitted_rate": ".fem.norms",
    # registered problems and runs
    "register": ".runs.registry",
    "Param": ".runs.registry",
    "Problem": ".runs.registry",
    "run": ".runs.runner",
    "available_problems": ".runs.registry",
    "get_problem": ".runs.registry",
    # distributed runs: which rank this process is under mpiexec (0 otherwise), for a script's output
    "launched_rank": ".distributed.launch",
}

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
    globals()[name] = value
    return value


def __dir__():
    return sorted({*globals(), *__all__})
