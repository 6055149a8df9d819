"""Geometry: background meshes (structured boxes, files), level sets, triangulated surfaces, the
cut of a mesh by a level set or by a domain of several (sides, element and facet sets, the surface
S_h, the boundary parts), measures and quadrature.  Each stage's compiled kernels sit beside it
(``*_kernels.py``, private)."""
