"""The peer's side at order 2: ngsxfem (NGSolve + xfem) with P2 fields on its isoparametric cut
geometry (Lehrenfeld, CMAME 300, 2016), on cutfem's own structured tets (the comparison and its
tables: :mod:`cutfem.studies.peers_order2`).

Geometry
--------
The tets are cutfem's Kuhn box handed to NGSolve as in :mod:`cutfem.studies.peers_ngsxfem`
(:class:`~cutfem.studies.peers_ngsxfem.NgBackground`).  The level set is cutfem's own function
(:func:`levelset_cf`: the sphere's |x| - R, the torus's sqrt(z^2 + (s - R)^2) - r) as a
CoefficientFunction; ``LevelSetMeshAdaptation(mesh, order=2)`` takes its P2 approximation phi_h2
(NGSolve's ``Set``: a local projection, not the nodal interpolant), the P1 interpolant phi_h1 of
that (``lset_p1``, zeros moved by ngsxfem's own 1e-14, not cutfem's snap), and the P2 deformation
Theta_h that maps {phi_h1 = 0} onto a third-order approximation of the surface (search direction
grad phi_h2, a discontinuous P2 field; the shift not limited, :data:`THRESHOLD`).  So phi_h1 is not
cutfem's P1 level set: within two spacings of the surface its nodal values differ from phi's by
O(h^3) (at most 2.7e-4 and 3.2e-5 on the sphere at spacings 0.2 and 0.1, 7.0e-3 and 9.7e-5 on the
torus), and the two codes' cut geometries differ at the order of the geometry error.  Every measure of the forms, loads and errors is taken on the
deformed mesh (``deformation=`` of ``dCut``, ``dx``, ``dFacetPatch``), so gradients, the normal
n_h = grad phi_h1 / |grad phi_h1| (of the deformed cut) and Jacobians are those of Theta_h.

The three problems
------------------
* :func:`ngsxfem_poisson_p2`: ``poisson-cut``'s problem (docs/math.md §8: unit ball, u = sin(pi
  x/2) cos(pi y/3) exp(z/2), symmetric Nitsche with gamma / h_T, h_T the longest edge, gamma = 40) with P2 on the
  HASNEG tets.  Ghost penalty at order 2, two forms: ``"patch"`` (default, ngsxfem's own higher
  order ghost penalty: gamma_g h_F^-2 (u_1 - u_2, v_1 - v_2) over the patch of the two tets of each
  ghost facet, the polynomial of one tet extended to the other) or ``"jumps"`` (docs/math.md §18:
  gamma_g h_F ([d_n u], [d_n v]) + gamma_g h_F^3 / 4 ([d_n^2 u], [d_n^2 v]), NGSolve's ``hesse``,
  which is exact on deformed elements but computed by numerical differentiation: the assembly takes 3.5
  times as long at spacing 0.1).  Solver: CG with Jacobi, as at order 1.
* :func:`ngsxfem_laplace_beltrami_p2`: ``laplace-beltrami-cut``'s problem on the unit sphere
  (-Lap_S u + u = f, u = x y + z at the closest point, docs/math.md §4) as TraceFEM: P2 on the cut
  tets, (P_h grad u, P_h grad v) + (u, v) on the deformed S_h, and the normal-gradient volume
  stabilization tau_N h_T^a (n_h . grad u, n_h . grad v) over the (deformed) cut tets (default
  tau_N = 1, a = 1, cutfem's defaults for ``--stabilization normal``).  Errors: L2(S_h) and
  ||P_h (grad_S u o p - grad u_h)||, as cutfem's.
* :func:`ngsxfem_mean_curvature_p2`: the mean curvature vector on the paper's cut torus (docs/math.md
  §3): (H, v)_{S_h} + tau_N h_T^a (n_h . grad H, n_h . grad v)_{cut tets} = (grad_{S_h} x,
  grad_{S_h} v)_{S_h}, component by component (H = -Lap_S x), with tau_N h_T^-1 = 1 / s (issue 48's choice:
  :data:`MEAN_CURVATURE_PARAMS`), the error ||H_h - H^e||_{L2(S_h)} and the area error |S_h| - 4 pi^2 R r.

Each returns the errors, unknowns, element counts and stage times: ``mesh`` (cutfem's box and the
NGSolve mesh), ``levelset`` (phi_h2, phi_h1, Theta_h), ``cut`` (CutInfo, element and facet sets,
compressed space), ``assembly``, ``solve``, ``errors``.  NGSolve runs single-threaded (no
``TaskManager``).
"""

from __future__ import annotations

import math
import time

from cutfem.geometry.shapes import Sphere, Torus
from cutfem.problems.laplace_beltrami import ORDER2_NORMAL

from .peers_ngsxfem import NgBackground, element_longest_edges, kuhn_face_h, poisson_exact_cf, torus_exact_cf

#: the order of the fields and of the deformation
ORDER = 2
#: quadrature orders: the forms and loads, the errors and geometric quantities (the deformed
#: elements' Jacobians are not polynomial: two more than the P2 products need)
FORM_ORDER, ERROR_ORDER = 4, 6
#: largest shift of the deformation, in units of h (ngsxfem's ``threshold``): none in effect.  A
#: limit of 0.1 (ngsxfem's fictitious-domain demos) cuts the shift short on the coarse torus: L2
#: error 0.68 at spacing 0.2 against 0.155 without (issue 48's 1.5e-1)
THRESHOLD = 1000.0
#: the Poisson comparison: Nitsche gamma = 10 k^2 (cutfem's 10 at k = 1; ngsxfem's demos' choice), cutfem's
#: ghost penalty gamma_g.  With gamma = 10 and the patch ghost penalty the P2 matrix is not positive
#: definite at spacings 0.2 and 0.1 (CG with Jacobi stalls at 5000 iterations; a direct solve gives L2 errors
#: 1.0e-3 and 1.0e-4 against 5.7e-5 at 0.1 with gamma = 40)
POISSON_PARAMS = {"gamma": 40.0, "gamma_g": 0.1}
GHOST_PENALTIES = ("patch", "jumps")
#: the Laplace-Beltrami comparison: cutfem's laplace-beltrami-cut with its order-2 default, the normal-gradient
#: term tau_N h_T^-1 with tau_N = 1 (ngsxfem's own choice)
LAPLACE_BELTRAMI_PARAMS = dict(zip(("tau_n", "normal_h_power"), ORDER2_NORMAL))
#: the mean curvature comparison: issue 48's normal-gradient stabilization 1 / s (s the spacing) written
#: as cutfem's tau_N h_T^a with h_T = sqrt(3) s, the longest edge of a Kuhn tet.  It reproduces the issue's
#: L2 errors 1.5e-1, 3.5e-2, 6.6e-3 at spacings 0.2, 0.1, 0.05; tau_N = 1 (weight 1 / h_T) gives 3.9e-2, 8.0e-3
#: at 0.1, 0.05
MEAN_CURVATURE_PARAMS = {"tau_n": math.sqrt(3.0), "normal_h_power": -1.0}
CG_TOL = 1e-10


def levelset_cf(shape):
    """cutfem's level set of a Sphere or a Torus (both centred anywhere) as an NGSolve
    CoefficientFunction: |x - c| - R, or sqrt(z^2 + (s - R)^2) - r with s = |(x, y) - c|."""
    from ngsolve import sqrt, x, y, z

    cx, cy, cz = (float(c) for c in shape.center)
    X, Y, Z = x - cx, y - cy, z - cz
    if isinstance(shape, Sphere):
        return sqrt(X * X + Y * Y + Z * Z) - shape.radius
    if isinstance(shape, Torus):
        s = sqrt(X * X + Y * Y)
        return sqrt(Z * Z + (s - shape.R) * (s - shape.R)) - shape.r
    raise ValueError(f"levelset_cf: a Sphere or a Torus, got {type(shape).__name__}")


class Isoparametric:
    """ngsxfem's order-2 isoparametric geometry of ``levelset`` on an :class:`NgBackground`:
    ``deformation`` (Theta_h - id, a P2 vector GridFunction), ``lset`` (phi_h1), the ``cut`` tets (IF),
    the ``hasneg`` tets and h_T (``hT``, longest edges, an order-0 L2 GridFunction).  Fills the
    stages ``levelset`` and ``cut`` of the timer dict ``T``."""

    def __init__(self, background, levelset, T, threshold=None):
        from ngsolve import L2, GridFunction
        from xfem import HASNEG, IF, CutInfo
        from xfem.lsetcurv import LevelSetMeshAdaptation

        mesh = self.mesh = background.mesh
        t0 = time.perf_counter()
        self.adaptation = LevelSetMeshAdaptation(mesh, order=ORDER, threshold=THRESHOLD if threshold is None else threshold, discontinuous_qn=True)
        self.deformation = self.adaptation.CalcDeformation(levelset_cf(levelset))
        self.lset = self.adaptation.lset_p1
        T["levelset"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        ci = CutInfo(mesh, self.lset)
        self.cut, self.hasneg = ci.GetElementsOfType(IF), ci.GetElementsOfType(HASNEG)
        self.hT = GridFunction(L2(mesh, order=0))
        self.hT.vec.FV().NumPy()[:] = element_longest_edges(mesh)
        T["cut"] = time.perf_counter() - t0

    def normal(self):
        """n_h = grad phi_h1 / |grad phi_h1|, the unit normal of the deformed cut where the mesh is deformed."""
        from ngsolve import InnerProduct, grad, sqrt

        g = grad(self.lset)
        return g / sqrt(InnerProduct(g, g))

    def measure(self, domain_type, elements, order=FORM_ORDER):
        """``dCut`` on the deformed mesh over ``elements``."""
        from xfem import dCut

        return dCut(levelset=self.lset, domain_type=domain_type, definedonelements=elements, deformation=self.deformation, order=order)

    def sizes(self) -> dict:
        return {"cut_tets": int(self.cut.NumSet()), "background_nodes": int(self.mesh.nv), "background_tets": int(self.mesh.ne),
                "max_deformation": float(abs(self.deformation.vec.FV().NumPy()).max())}


def _compressed_space(mesh, elements, dgjumps=False):
    import ngsolve as ngs
    from xfem import GetDofsOfElements

    V = ngs.H1(mesh, order=ORDER, dgjumps=dgjumps)
    return ngs.Compress(V, GetDofsOfElements(V, elements))


def _record(T, **values) -> dict:
    return dict(values, time=T, total=sum(T.values()))


def ngsxfem_poisson_p2(spacing, levelset=None, gamma=POISSON_PARAMS["gamma"], gamma_g=POISSON_PARAMS["gamma_g"], ghost="patch",
                       inverse="cg-local", background=None) -> dict:
    """Fictitious-domain Poisson (``poisson-cut``'s data) with P2 on ngsxfem's isoparametric cut of
    cutfem's structured background.  ``ghost``: "patch" or "jumps" (the module docstring);
    ``inverse``: "cg-" + an NGSolve preconditioner name (CG to a relative residual of
    :data:`CG_TOL`) or an NGSolve direct inverse ("sparsecholesky")."""
    import ngsolve as ngs
    from ngsolve import CF, GridFunction, InnerProduct, Integrate, LinearForm, grad, specialcf
    from xfem import IF, NEG, GetFacetsWithNeighborTypes, RestrictedBilinearForm, dFacetPatch

    if ghost not in GHOST_PENALTIES:
        raise ValueError(f"ghost must be one of {GHOST_PENALTIES}, got {ghost!r}")
    levelset = Sphere() if levelset is None else levelset
    T = {}
    background = NgBackground(spacing, levelset) if background is None else background
    T["mesh"] = background.seconds
    geo = Isoparametric(background, levelset, T)
    mesh, d, hT = geo.mesh, geo.deformation, geo.hT
    t0 = time.perf_counter()
    ghost_facets = GetFacetsWithNeighborTypes(mesh, a=geo.hasneg, b=geo.cut, bnd_val_a=False, bnd_val_b=False, use_and=True)
    V = _compressed_space(mesh, geo.hasneg, dgjumps=True)
    T["cut"] += time.perf_counter() - t0

    t0 = time.perf_counter()
    u_ex, grad_ex, f = poisson_exact_cf()
    u, v = V.TnT()
    n = geo.normal()
    dxn, ds = geo.measure(NEG, geo.hasneg), geo.measure(IF, geo.cut)
    hF = kuhn_face_h(spacing)
    a = RestrictedBilinearForm(V, element_restriction=geo.hasneg, facet_restriction=ghost_facets, symmetric=True, check_unused=False)
    a += InnerProduct(grad(u), grad(v)) * dxn
    a += (-InnerProduct(grad(u), n) * v - InnerProduct(grad(v), n) * u + gamma / hT * u * v) * ds
    if ghost == "patch":
        a += gamma_g / hF**2 * (u - u.Other()) * (v - v.Other()) * dFacetPatch(definedonelements=ghost_facets, deformation=d)
    else:
        nF = specialcf.normal(3)
        dw = ngs.dx(skeleton=True, definedonelements=ghost_facets, deformation=d)

        def jump1(w):
            return InnerProduct(grad(w) - grad(w.Other()), nF)

        def jump2(w):
            return InnerProduct((w.Operator("hesse") - w.Other().Operator("hesse")) * nF, nF)

        a += (gamma_g * hF * jump1(u) * jump1(v)).Compile() * dw
        a += (gamma_g * hF**3 / 4 * jump2(u) * jump2(v)).Compile() * dw  # compiled: 3 times faster
    pre = ngs.Preconditioner(a, inverse[3:]) if inverse.startswith("cg-") else None
    a.Assemble()
    b = LinearForm(V)
    b += f * v * dxn
    b += u_ex * (-InnerProduct(grad(v), n) + gamma / hT * v) * ds
    b.Assemble()
    T["assembly"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if pre is None:
        inv = a.mat.Inverse(V.FreeDofs(), inverse=inverse)
    else:
        inv = ngs.solvers.CGSolver(a.mat, pre.mat, tol=CG_TOL, maxiter=20000)
    uh = GridFunction(V)
    uh.vec.data = inv * b.vec
    T["solve"] = time.perf_counter() - t0
    iterations = getattr(inv, "iterations", 0)
    del inv

    t0 = time.perf_counter()
    dxe = geo.measure(NEG, geo.hasneg, ERROR_ORDER)
    e, eg = uh - u_ex, grad(uh) - grad_ex
    l2 = math.sqrt(Integrate(e * e * dxe, mesh))
    h1 = math.sqrt(Integrate(InnerProduct(eg, eg) * dxe, mesh))
    T["errors"] = time.perf_counter() - t0
    volume = Integrate(CF(1.0) * dxe, mesh)
    return _record(T, l2_error=l2, h1_error=h1, volume=volume, volume_error=abs(volume - levelset.volume), dofs=int(V.ndof),
                   active_tets=int(geo.hasneg.NumSet()), ghost_faces=int(ghost_facets.NumSet()), **geo.sizes(), ghost_penalty=ghost,
                   solver=inverse, solver_iterations=int(iterations))


def sphere_solution_cf(radius=1.0):
    """(u, f, grad_S u) of laplace-beltrami-cut's sphere solution (u = x y + z at the closest point
    q = R x / |x|, f = (6/R^2 + 1) q_x q_y + (2/R^2 + 1) q_z, grad_S u = P(q) (q_y, q_x, 1)) as NGSolve
    CoefficientFunctions."""
    from ngsolve import CF, Id, OuterProduct, sqrt, x, y, z

    r = sqrt(x * x + y * y + z * z)
    qx, qy, qz = radius * x / r, radius * y / r, radius * z / r
    u = qx * qy + qz
    f = (6 / radius**2 + 1) * qx * qy + (2 / radius**2 + 1) * qz
    m = CF((x / r, y / r, z / r))
    grad_s = (Id(3) - OuterProduct(m, m)) * CF((qy, qx, 1.0))
    return u, f, grad_s


def _normal_gradient(geo, u, v, tau_n, h_power):
    """tau_N h_T^a (n_h . grad u, n_h . grad v) over the deformed cut tets."""
    import ngsolve as ngs
    from ngsolve import InnerProduct, grad

    n = geo.normal()
    return tau_n * geo.hT**h_power * InnerProduct(grad(u), n) * InnerProduct(grad(v), n) * ngs.dx(
        definedonelements=geo.cut, deformation=geo.deformation, bonus_intorder=2)


def _trace_setup(spacing, levelset, box, background, T):
    """The peer's isoparametric cut of ``levelset`` and its P2 trace space on the cut elements:
    (geometry, mesh, space), the mesh's and the cut's seconds into ``T``."""
    background = NgBackground(spacing, levelset, box) if background is None else background
    T["mesh"] = background.seconds
    geo = Isoparametric(background, levelset, T)
    t0 = time.perf_counter()
    V = _compressed_space(geo.mesh, geo.cut)
    T["cut"] += time.perf_counter() - t0
    return geo, geo.mesh, V


def ngsxfem_laplace_beltrami_p2(spacing, levelset=None, tau_n=LAPLACE_BELTRAMI_PARAMS["tau_n"],
                                normal_h_power=LAPLACE_BELTRAMI_PARAMS["normal_h_power"], inverse="sparsecholesky", background=None) -> dict:
    """TraceFEM -Lap_S u + u = f on the sphere (``laplace-beltrami-cut``'s data) with P2 on
    ngsxfem's isoparametric cut, normal-gradient stabilized (the module docstring)."""
    from ngsolve import CF, GridFunction, Id, InnerProduct, Integrate, LinearForm, OuterProduct, grad
    from xfem import IF, RestrictedBilinearForm

    levelset = Sphere() if levelset is None else levelset
    T = {}
    geo, mesh, V = _trace_setup(spacing, levelset, None, background, T)

    t0 = time.perf_counter()
    u_ex, f, grad_ex = sphere_solution_cf(levelset.radius)
    u, v = V.TnT()
    n = geo.normal()
    P = Id(3) - OuterProduct(n, n)
    ds = geo.measure(IF, geo.cut)
    a = RestrictedBilinearForm(V, element_restriction=geo.cut, symmetric=True, check_unused=False)
    a += (InnerProduct(P * grad(u), P * grad(v)) + u * v) * ds
    a += _normal_gradient(geo, u, v, tau_n, normal_h_power)
    a.Assemble()
    b = LinearForm(V)
    b += f * v * geo.measure(IF, geo.cut, ERROR_ORDER)
    b.Assemble()
    T["assembly"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    uh = GridFunction(V)
    uh.vec.data = a.mat.Inverse(V.FreeDofs(), inverse=inverse) * b.vec
    T["solve"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    dse = geo.measure(IF, geo.cut, ERROR_ORDER)
    e, eg = uh - u_ex, P * (grad_ex - grad(uh))
    l2 = math.sqrt(Integrate(e * e * dse, mesh))
    h1 = math.sqrt(Integrate(InnerProduct(eg, eg) * dse, mesh))
    T["errors"] = time.perf_counter() - t0
    area = Integrate(CF(1.0) * dse, mesh)
    return _record(T, l2_error=l2, h1_error=h1, area=area, area_error=abs(area - levelset.area), dofs=int(V.ndof),
                   active_tets=int(geo.cut.NumSet()), **geo.sizes(), tau_n=tau_n, normal_h_power=normal_h_power, solver=inverse)


def ngsxfem_mean_curvature_p2(spacing, levelset=None, box=None, tau_n=MEAN_CURVATURE_PARAMS["tau_n"],
                              normal_h_power=MEAN_CURVATURE_PARAMS["normal_h_power"], inverse="sparsecholesky", background=None) -> dict:
    """The mean curvature vector on the cut torus (``mean-curvature-cut``'s problem, the paper's
    box) with P2 on ngsxfem's isoparametric cut, normal-gradient stabilized: one factorization, three
    solves (the module docstring)."""
    import ngsolve as ngs
    from ngsolve import CF, GridFunction, Id, InnerProduct, Integrate, LinearForm, OuterProduct, grad
    from xfem import IF, RestrictedBilinearForm

    levelset = Torus() if levelset is None else levelset
    T = {}
    geo, mesh, V = _trace_setup(spacing, levelset, box, background, T)

    t0 = time.perf_counter()
    u, v = V.TnT()
    n = geo.normal()
    P = Id(3) - OuterProduct(n, n)
    ds = geo.measure(IF, geo.cut)
    a = RestrictedBilinearForm(V, element_restriction=geo.cut, symmetric=True, check_unused=False)
    a += u * v * ds
    a += _normal_gradient(geo, u, v, tau_n, normal_h_power)
    a.Assemble()
    rhs = []
    for k in range(3):  # (grad_S x_k, grad_S v) = ((P grad v)_k, 1)
        b = LinearForm(V)
        b += (P * grad(v))[k] * ds
        b.Assemble()
        rhs.append(b)
    T["assembly"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    inv = a.mat.Inverse(V.FreeDofs(), inverse=inverse)
    H = []
    for b in rhs:
        gf = GridFunction(V)
        gf.vec.data = inv * b.vec
        H.append(gf)
    T["solve"] = time.perf_counter() - t0
    del inv

    t0 = time.perf_counter()
    dse = geo.measure(IF, geo.cut, ERROR_ORDER)
    diff = ngs.CF(tuple(H)) - torus_exact_cf(levelset)
    l2 = math.sqrt(Integrate(InnerProduct(diff, diff) * dse, mesh))
    T["errors"] = time.perf_counter() - t0
    area = Integrate(CF(1.0) * dse, mesh)
    return _record(T, l2_error=l2, area=area, area_error=abs(area - levelset.area), dofs=int(V.ndof), dofs_total=3 * int(V.ndof),
                   active_tets=int(geo.cut.NumSet()), **geo.sizes(), tau_n=tau_n, normal_h_power=normal_h_power, solver=inverse)
