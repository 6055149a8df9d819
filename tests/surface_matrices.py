"""The surface matrices of a trace or meshed field, assembled from the public forms: shared by the
tests (imported as a plain module from this folder)."""

from cutfem.fem.forms import assemble
from cutfem.fem.terms import edge_jump_penalty, face_jump_penalty, load, mass, tangential_stiffness
from cutfem.geometry.markers import CUT
from cutfem.geometry.measures import surface_measure


def dF(V):
    """The facet measure of J_F: the interior faces of the cut tets."""
    return V.cut.dF(V.cut.interior_facets(CUT))


def mass_matrix(V):
    return assemble(mass(surface_measure(V)), V)


def stiffness_matrix(V):
    return assemble(tangential_stiffness(surface_measure(V)), V)


def edge_matrix(V, **kw):
    return assemble(edge_jump_penalty(surface_measure(V), **kw), V)


def face_matrix(V, **kw):
    return assemble(face_jump_penalty(dF(V), **kw), V)


def load_vector(V, f, **kw):
    return assemble(load(f, surface_measure(V), **kw), V)
