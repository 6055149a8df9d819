"""Index conventions shared by the mesh code and the compiled kernels (the lowest layer: numpy only).

* :data:`TET_FACES`, :data:`TET_EDGES`: the local numbering of a tetrahedron's faces (face k is
  opposite to vertex k) and edges (the pairs (0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)), in
  which element matrices on the edges and faces are laid out;
* :data:`CUBE_CORNERS`: the local numbering of a cube's corners (corner c at the offset of its
  bits), in which the cells of a structured box and their Kuhn tets are laid out;
* :func:`index_dtype`: the integer type of the index arrays the library makes.
"""

from __future__ import annotations

import numpy as np

__all__ = ["TET_FACES", "TET_EDGES", "CUBE_CORNERS", "index_dtype"]

#: local faces of a tet, face k opposite to vertex k
TET_FACES = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]], dtype=np.int64)
#: local edges of a tet
TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)
#: (8, 3) the corners of the unit cube: corner c has the offset ((c>>0)&1, (c>>1)&1, (c>>2)&1)
CUBE_CORNERS = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=np.int64)


def index_dtype(largest) -> type:
    """np.int32 when integers up to ``largest`` fit in it, else np.int64: the type of the index
    arrays the library makes (node and element numbers, CSR indices, sort orders), which halves
    their memory and traffic wherever the sizes allow."""
    return np.int32 if largest < 2**31 else np.int64
