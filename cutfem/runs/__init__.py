"""Runs: the problem registry and its parameters, the run over levels and its records, the
``cutfem`` command line, convergence tables and plots."""
