"""The tests mirror the package's layout (tests/geometry, tests/fem, ...); this folder is put on
sys.path by pytest for this file, so the shared reference assemblies (surface_matrices.py) are
importable from every subfolder."""
