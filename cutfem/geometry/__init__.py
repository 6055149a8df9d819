"""Geometry: background meshes (structured boxes, files), level sets, triangulated surfaces, the
cut of a mesh by a level set (sides, element and facet sets, the surface S_h), measures and
quadrature.  Each stage's compiled kernels sit beside it (``*_kernels.py``, private)."""
