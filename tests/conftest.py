"""The tests mirror the package's layout (tests/geometry, tests/fem, ...); this folder is put on
sys.path by pytest for this file, so the shared references (surface_matrices.py, the reference
assemblies; levelset_references.py, the level-set tests' independent geometry) are importable from
every subfolder."""
