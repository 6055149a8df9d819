"""The pieces of a moving-domain step (cutfem.fem.moving): the shifted level set, the extended
domain and its strip facets against brute-force definitions, the transfer between spaces, the
Nitsche term of a field on the extended domain against that of the domain's own field, and the
refusals that name the fix."""

import numpy as np
import pytest

import cutfem as cf
from cutfem.fem.moving import ActiveDomain, Shifted, strip_width, transfer
from cutfem.fem.terms import nitsche

BOX = cf.structured_box([-1.0] * 3, [1.0] * 3, spacing=0.125)


def test_shifted_sphere_is_the_larger_sphere():
    x = np.random.default_rng(0).uniform(-1, 1, (100, 3))
    S = Shifted(cf.Sphere(0.5, (0.1, 0, 0)), 0.2)
    np.testing.assert_allclose(S.value(x), cf.Sphere(0.7, (0.1, 0, 0)).value(x), atol=1e-15)
    np.testing.assert_array_equal(S.gradient(x), cf.Sphere(0.5, (0.1, 0, 0)).gradient(x))
    a, b = cf.cut_mesh(BOX, S), cf.cut_mesh(BOX, cf.Sphere(0.7, (0.1, 0, 0)))
    assert abs(a.dx(cf.NEG).size - b.dx(cf.NEG).size) < 1e-12


def test_extended_domain_and_strip_facets_by_definition():
    phi = cf.Sphere(0.5, (0.05, -0.02, 0.01))
    delta = 0.15
    d = ActiveDomain(BOX, phi, delta)
    es = d.space.elements
    values = phi.value(es.points)  # phi at the extended set's nodes
    assert np.all(values[es.tets].min(axis=1) < delta)  # every tet meets {phi < delta}
    assert np.all(es.contains(d.cut.elements(cf.CUT).tet_ids))  # and the set holds the domain's cut tets
    strip = values[es.tets].max(axis=1) > -delta
    pairs = d.strip_facets.pairs
    assert np.all(strip[pairs[:, 0]] | strip[pairs[:, 1]])
    every = d.extended.interior_facets(cf.NEG).pairs
    assert len(pairs) == int(np.sum(strip[every[:, 0]] | strip[every[:, 1]])) > 0


def test_transfer_keeps_the_shared_nodes_and_checks_the_cover():
    a = ActiveDomain(BOX, cf.Sphere(0.5, (-0.1, 0, 0)), 0.2)
    b = ActiveDomain(BOX, cf.Sphere(0.5, (0.0, 0, 0)), 0.2)
    u = a.space.interpolate(lambda x: 1 + x[:, 0] + 2 * x[:, 1])
    v = transfer(u, a.space, b.space, over=b.dx)
    shared = np.isin(b.space.node_ids, a.space.node_ids)
    np.testing.assert_array_equal(v[shared], b.space.interpolate(lambda x: 1 + x[:, 0] + 2 * x[:, 1])[shared])
    assert np.all(v[~shared] == 0)
    far = ActiveDomain(BOX, cf.Sphere(0.5, (0.3, 0, 0)), 0.05)  # moved 0.4 with a strip of 0.05
    with pytest.raises(ValueError, match="moved farther than the strip is wide"):
        transfer(transfer(u, a.space, a.space), a.space, far.space, over=far.dx)
    with pytest.raises(ValueError, match="u has 3 values"):
        transfer(np.zeros(3), a.space, b.space)


def test_nitsche_on_the_extended_field_is_the_domains_own():
    phi = cf.Sphere(0.5, (0.05, -0.02, 0.01))
    d = ActiveDomain(BOX, phi, 0.15)
    own = cf.CutSpace(d.cut, cf.NEG)
    Ke = cf.assemble(nitsche(d.ds, 10.0), d.space)
    Ko = cf.assemble(nitsche(d.ds, 10.0), own)
    pos = np.searchsorted(d.space.node_ids, own.node_ids)
    assert np.all(d.space.node_ids[pos] == own.node_ids)
    np.testing.assert_allclose(Ke[pos][:, pos].toarray(), Ko.toarray(), atol=1e-13 * abs(Ko).max())
    rest = np.setdiff1d(np.arange(d.space.n_dofs), pos)
    assert abs(Ke[rest]).max() == 0  # nodes outside the domain's tets do not see Gamma


def test_refusals():
    with pytest.raises(ValueError, match="positive finite"):
        ActiveDomain(BOX, cf.Sphere(0.5), 0.0)
    with pytest.raises(ValueError, match="order is 1 or 2"):
        strip_width(1.0, 0.1, 3)
    with pytest.raises(ValueError, match="dt must be a positive"):
        strip_width(1.0, -0.1, 1)
    other = cf.cut_mesh(BOX, cf.Sphere(0.3))
    small = cf.CutSpace(other, cf.NEG)  # does not hold the cut tets of the larger sphere
    with pytest.raises(ValueError, match="do not hold every cut tet"):
        cf.assemble(nitsche(cf.cut_mesh(BOX, cf.Sphere(0.6)).ds(), 10.0), small)
