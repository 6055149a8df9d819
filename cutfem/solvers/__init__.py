"""Linear solvers: :func:`cutfem.solvers.solve.solve` chooses a direct factorization or CG with
geometric multigrid and diagnoses singular and indefinite systems.  Compiled sparse kernels sit
beside them (``*_kernels.py``, private)."""
