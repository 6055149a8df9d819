"""Linear solvers: :func:`cutfem.solvers.solve.solve` checks the system and chooses a direct
factorization (:mod:`~cutfem.solvers.direct`) or conjugate gradients (:mod:`~cutfem.solvers.krylov`)
with geometric multigrid (:mod:`~cutfem.solvers.multigrid`); a system that is not positive definite
is refused with its cause (:mod:`~cutfem.solvers.diagnose`).  :mod:`~cutfem.solvers.common` holds
what they share; compiled sparse kernels sit beside them (``*_kernels.py``, private)."""
