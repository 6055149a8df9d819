"""Runs: the problem registry and its parameters (registry), the run over levels and its records
(runner), the ``cutfem`` command line, convergence tables and plots."""
