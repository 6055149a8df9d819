"""Finite elements on the geometry: P1 spaces on element sets and surfaces, the form language and
its built-in terms, assembly into sparse matrices, and error norms.  Compiled kernels sit beside
their stage (``*_kernels.py``, private)."""
