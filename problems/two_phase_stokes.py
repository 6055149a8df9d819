"""Two-phase Stokes flow with surface tension: the static bubble (Hansbo-Larson-Zahedi, APNUM 85,
2014; docs/math.md §15).

-div(2 mu_i eps(u)) + grad p = 0, div u = 0 in Omega_i (NEG inside the sphere |x| = R, POS outside,
in the box), [u] = 0 and (sigma_POS - sigma_NEG) n = tau H on Gamma, u = 0 on the box, sigma =
2 mu eps(u) - p I, n from NEG to POS, H = (k1 + k2) n = (2 / R) n.  Exact: u = 0, p piecewise
constant with p_NEG - p_POS = 2 tau / R.

Unknowns (u_NEG, u_POS, p_NEG, p_POS, lam) in [V_h^NEG]^3 x [V_h^POS]^3 x V_h^NEG x V_h^POS x R, for
all (v_NEG, v_POS, q_NEG, q_POS, m):

    sum_i (2 mu_i eps(u_i), eps(v_i))_i - ({2 mu eps(u) n}, [v]) - ({2 mu eps(v) n}, [u]) + (lambda / h) ([u], [v])
      - sum_i (div v_i, p_i)_i + ({p}, [v . n]) - sum_i (div u_i, q_i)_i + ({q}, [u . n])
      + sum_i mu_i gamma_u g_1,i(u_i, v_i) - sum_i (1 / mu_i) (gamma_p g_3,i + beta h^2 (grad ., grad .)_i)(p_i, q_i)
      + sum_i (p_i, m)_i + sum_i (q_i, lam)_i
    = -tau (H, <v>)_Gamma_h,

[w] = w_NEG - w_POS, {w} = k_NEG w_NEG + k_POS w_POS with the harmonic weights k_NEG = mu_POS /
(mu_NEG + mu_POS) (docs/math.md §9, with the coefficient 2 mu), lambda = 2 gamma (k_NEG^2 2 mu_NEG +
k_POS^2 2 mu_POS) = gamma times the harmonic mean of 2 mu; g_a,i the ghost penalties on the faces
G_i (h_F^a times the jumps of the normal derivatives); u_POS = 0 strongly at the box's nodes.

The load pairs the interface condition with the dual average <v> = k_POS v_NEG + k_NEG v_POS:
integrating each side by parts, -(sigma_NEG n, v_NEG) + (sigma_POS n, v_POS) = -({sigma n}, [v])
- ([sigma n], <v>), and [sigma n] = -tau H.  (For a continuous v, <v> = {v} = v; the dual weights
make the discrete equations consistent for the exact piecewise constant pressure, whose jump meets
exactly <v> . n.)  H is, by ``curvature``:

* ``discrete``: H_h, the stabilized mean curvature vector of docs/math.md §3 on the same cut
  (CutSpace(cut, CUT), tau_F J_F on the interior faces of the cut tets), solved first, its trace
  paired with <v> by the coupling matrix of the trace space and the velocities on Gamma_h;
* ``laplace-beltrami``: (H, v) = (grad_Gamma x, grad_Gamma v) = (div_Gamma v, 1) on the pieces of
  Gamma_h, no curvature computed.

The saddle system is solved by MINRES with diag(multigrid on both velocities, S_NEG, S_POS), S_i =
(1 / mu_i) M_i + the side's pressure stabilization, the multiplier by its Schur number
(:mod:`cutfem.solvers.saddle`), or factorized when small.
"""

from __future__ import annotations

import numpy as np

from cutfem.fem.coupling import divergence, mean_constraint
from cutfem.fem.elasticity import elasticity
from cutfem.fem.forms import assemble, bilinear_form, linear_form
from cutfem.fem.norms import l2_error
from cutfem.fem.pointwise import ZERO, dot
from cutfem.fem.spaces import CutSpace, ProductSpace, RealSpace, VectorSpace
from cutfem.fem.terms import apply_dirichlet, basis_integrals, face_jump_penalty, mass, stiffness
from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.markers import CUT, NEG, POS
from cutfem.geometry.shapes import Sphere
from cutfem.runs.registry import H_BACKGROUND, LazyFields, Param, ProblemError, register
from cutfem.runs.runner import Timer
from cutfem.solvers.solve import solve

from .common import finish_record, background_for, check_ghost_penalty, check_nitsche_penalty, check_resolution, pin_unseen_nodes
from .mean_curvature import mean_curvature_system

#: the positions of the fields in the product space
U_NEG, U_POS, P_NEG, P_POS, MEAN = range(5)
#: relative residual of the curvature solve: H_h enters the load, so well below the Stokes solve's 1e-8
CURVATURE_TOL = 1e-10

DEFINITIONS = {
    "h": H_BACKGROUND,
    "dofs": "unknowns: 3 velocity components and the pressure on the nodes of the tets of NEG and of POS, and the multiplier",
    "l2_error_velocity": "the spurious currents, ||u_h||_L2 over both sides (exact u = 0; degree-4 quadrature on the cut volumes)",
    "pressure_jump_error": "|mean p_NEG - mean p_POS - 2 tau / R| / (2 tau / R), the means over the cut volumes of each side",
}


def _weights(mu_neg, mu_pos):
    """The harmonic weights (k_NEG, k_POS) and lambda / gamma = 2 (k_NEG^2 2 mu_NEG + k_POS^2 2 mu_POS)."""
    k_neg = mu_pos / (mu_neg + mu_pos)
    k_pos = 1.0 - k_neg
    return k_neg, k_pos, 2.0 * (k_neg**2 * 2.0 * mu_neg + k_pos**2 * 2.0 * mu_pos)


@bilinear_form(symmetric=True)
def _interface(u, v, w):
    """Nitsche-XFEM on Gamma_h: -({2 mu eps(u) n}, [v]) - ({2 mu eps(v) n}, [u]) + (lambda / h) ([u], [v])
    + ({p}, [v . n]) + ({q}, [u . n]), parameters k_neg, k_pos, mu_neg, mu_pos and lam (= lambda)."""
    n = w.n

    def traction(f):
        return w.k_neg * 2.0 * w.mu_neg * dot(f[U_NEG].sym_grad, n) + w.k_pos * 2.0 * w.mu_pos * dot(f[U_POS].sym_grad, n)

    def average_pressure(f):
        return w.k_neg * f[P_NEG] + w.k_pos * f[P_POS]

    ju, jv = u[U_NEG] - u[U_POS], v[U_NEG] - v[U_POS]
    return (-dot(traction(u), jv) - dot(traction(v), ju) + (w.lam / w.h) * dot(ju, jv)
            + average_pressure(u) * dot(jv, n) + average_pressure(v) * dot(ju, n))


@bilinear_form(symmetric=True)
def _curvature_pairing(u, v, w):
    """(H, <v>) + (<u>, G) on Gamma_h between the field 0 (the curvature, on the cut tets) and the
    velocities 1, 2 (NEG, POS): its (velocity, curvature) block times H_h is the load's (H_h, <v>)."""

    def dual_average(f):
        return w.k_pos * f[1] + w.k_neg * f[2]

    return dot(u[0], dual_average(v)) + dot(v[0], dual_average(u))


@linear_form(degree=1)
def _laplace_beltrami_load(v, w):
    """(grad_Gamma x, grad_Gamma <v>) = (div_Gamma <v>, 1) on the pieces of Gamma_h: the trace of the
    rows' tangential gradients grad v P_h (constant on a piece)."""
    tg = w.k_pos * v[U_NEG].tgrad + w.k_neg * v[U_POS].tgrad
    if tg is ZERO:
        return ZERO
    return np.einsum("...ii->...", tg)


def discrete_curvature(cut, tau_f):
    """H_h (n, 3) on CutSpace(cut, CUT) (docs/math.md §3, tau_E = 0, tau_F J_F with h^0), and the space."""
    Vc = CutSpace(cut, CUT)
    K, B = mean_curvature_system(Vc, cut.ds(), tau_f=tau_f, faces=cut.dF(cut.interior_facets(CUT)))
    K, B, _ = pin_unseen_nodes(K, B, Vc)
    H, _ = solve(K, B, space=Vc, tol=CURVATURE_TOL)
    return Vc, H


def surface_tension_load(cut, W, curvature, tau, k_neg, k_pos, tau_f=0.1):
    """The right-hand side -tau (H, <v>)_Gamma_h on the product space ``W`` (velocity rows only)."""
    ds = cut.ds()
    b = np.zeros(W.n_dofs)
    if curvature == "laplace-beltrami":
        return -tau * assemble(_laplace_beltrami_load * ds, W, k_neg=k_neg, k_pos=k_pos)
    if curvature != "discrete":
        raise ProblemError(f"--curvature must be 'discrete' or 'laplace-beltrami', got {curvature!r}")
    Vc, H = discrete_curvature(cut, tau_f)
    Hc = VectorSpace(Vc)
    Z = ProductSpace(Hc, W[U_NEG], W[U_POS])
    C = assemble(_curvature_pairing * ds, Z, k_neg=k_neg, k_pos=k_pos).tocsr()
    pairing = C[Z.offsets[1]:, :Z.offsets[1]] @ Hc.flat(H)
    b[W.offsets[U_NEG]:W.offsets[U_POS + 1]] = -tau * pairing
    return b


@register(
    "two-phase-stokes-cut",
    summary="static bubble: two-phase Stokes with surface tension from the discrete mean curvature vector or Laplace-Beltrami, "
            "Nitsche-XFEM (docs/math.md §15)",
    levels=[0.2, 0.1, 0.05],
    level_name="spacing",
    definitions=DEFINITIONS,
    params=[
        Param("curvature", str, "discrete", "surface tension: discrete (-tau (H_h, v), H_h of docs/math.md §3) or "
              "laplace-beltrami (-tau (grad_Gamma x, grad_Gamma v))", choices=("discrete", "laplace-beltrami")),
        Param("radius", float, 0.5, "radius R of the bubble", positive=True),
        Param("box", str, "-1,-1,-1,1,1,1", "background box x0,y0,z0,x1,y1,z1"),
        Param("mu_inside", float, 1.0, "viscosity in the bubble (NEG)", positive=True),
        Param("mu_outside", float, 1.0, "viscosity outside (POS)", positive=True),
        Param("tau", float, 1.0, "surface tension tau", minimum=0),
        Param("gamma", float, 20.0, "Nitsche penalty gamma (times the harmonic mean of 2 mu)", positive=True),
        Param("gamma_u", float, 0.1, "ghost penalty of the velocity (times mu_i, h_F)", minimum=0),
        Param("gamma_p", float, 0.1, "ghost penalty of the pressure (over mu_i, h_F^3)", minimum=0),
        Param("beta", float, 0.05, "Brezzi-Pitkaranta pressure stabilization beta (over mu_i, h_T^2)", positive=True),
        Param("tau_f", float, 0.1, "face stabilization tau_F of the discrete curvature", positive=True),
        Param("solver", str, "auto", "linear solver: auto (direct up to 5000 unknowns), minres or direct",
              choices=("auto", "minres", "direct")),
    ],
)
def two_phase_stokes_cut(spacing, curvature, radius, box, mu_inside, mu_outside, tau, gamma, gamma_u, gamma_p, beta, tau_f,
                         solver):
    """One level of the static bubble."""
    notes = check_ghost_penalty(gamma_u, "--gamma-u") + check_ghost_penalty(gamma_p, "--gamma-p") + check_nitsche_penalty(gamma)
    mu = {NEG: mu_inside, POS: mu_outside}
    k_neg, k_pos, two_s = _weights(mu_inside, mu_outside)
    t = Timer()
    with t("geometry"):
        phi = Sphere(radius)
        bg = background_for(phi, spacing, "structured", box)
        cut = cut_mesh(bg, phi)
        check_resolution(cut, phi, spacing)
        V = {side: CutSpace(cut, side) for side in (NEG, POS)}
        W = ProductSpace(u_neg=VectorSpace(V[NEG]), u_pos=VectorSpace(V[POS]), p_neg=V[NEG], p_pos=V[POS], mean=RealSpace())
        ds = cut.ds()
    with t("assembly"):
        a = _interface.on(ds, k_neg=k_neg, k_pos=k_pos, mu_neg=mu_inside, mu_pos=mu_outside, lam=gamma * two_s)
        schur = {}
        for side, ku, kp in ((NEG, U_NEG, P_NEG), (POS, U_POS, P_POS)):
            dx, dg = cut.dx(side), cut.dF(cut.ghost_facets(side))
            a = a + elasticity(dx, mu[side], 0.0, field=ku) + divergence(dx, ku, kp) + mean_constraint(dx, kp, MEAN) \
                - (beta / mu[side]) * stiffness(dx, field=kp, h_power=2)
            s = (1 / mu[side]) * mass(dx) + (beta / mu[side]) * stiffness(dx, h_power=2)
            if gamma_u > 0:
                a = a + mu[side] * gamma_u * face_jump_penalty(dg, h_power=1, field=ku)
            if gamma_p > 0:
                a = a - (gamma_p / mu[side]) * face_jump_penalty(dg, h_power=3, field=kp)
                s = s + (gamma_p / mu[side]) * face_jump_penalty(dg, h_power=3)
            schur[W.names[kp]] = assemble(s, V[side])
        K = assemble(a, W)
        b = surface_tension_load(cut, W, curvature, tau, k_neg, k_pos, tau_f)
        wall = W.offsets[U_POS] + W[U_POS].boundary_dofs
        K, b = apply_dirichlet(K, b, wall, 0.0)
    with t("solve"):
        x, info = solve(K, b, method=solver, space=W, primal=["u_neg", "u_pos"], schur=schur)
        u_neg, u_pos, p_neg, p_pos, _ = W.split(x)
    with t("errors"):
        zero = lambda y: np.zeros(y.shape)  # noqa: E731 (the exact velocity)
        l2 = [l2_error(W[k], u, zero, cut.dx(side)) for k, side, u in ((U_NEG, NEG, u_neg), (U_POS, POS, u_pos))]
        means = [float(assemble(basis_integrals(cut.dx(side)), V[side]) @ p) / cut.dx(side).size
                 for side, p in ((NEG, p_neg), (POS, p_pos))]
        jump = 2.0 * tau / radius
        rec = {
            "h": W.h,
            "dofs": int(W.n_dofs),
            "l2_error_velocity": float(np.hypot(*l2)),
            "pressure_jump": means[0] - means[1],
            "solver": info.method,
            "solver_iterations": info.iterations,
        }
        if tau > 0:
            rec["pressure_jump_error"] = abs(means[0] - means[1] - jump) / jump
    finish_record(rec, cut, W, notes, t)
    rec["fields"] = LazyFields(lambda: {
        "inside": V[NEG].elements.to_pyvista(u_h=W[U_NEG].nodal(u_neg), p_h=p_neg),
        "outside": V[POS].elements.to_pyvista(u_h=W[U_POS].nodal(u_pos), p_h=p_pos),
        "interface": cut.to_pyvista(),
    })
    return rec
