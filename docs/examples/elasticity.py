"""Linear elasticity in a ball, a vector field cut from a box: Nitsche and a ghost penalty.

    -div sigma(u) = f in Omega = {|x| < 1},   u = g on Gamma,
    sigma(u) = 2 mu eps(u) + lam (div u) I,   eps(u) = (grad u + grad u^T) / 2.

The displacement is one field of 3 components, VectorSpace(V) of the P1 space on the tets that
meet the ball (3 n unknowns, component after component).  The weak form:

    a(u, v) = (2 mu eps(u), eps(v)) + (lam div u, div v)                      elasticity
              - (sigma(u) n, v)_Gamma - (u, sigma(v) n)_Gamma
              + (2 mu + lam) gamma / h (u, v)_Gamma                             elasticity_nitsche
              + (2 mu + lam) gamma_g sum_F h_F ([grad u n_F], [grad v n_F])_F   face_jump_penalty, per component
    l(v)    = (f, v) - (g, sigma(v) n)_Gamma + (2 mu + lam) gamma / h (g, v)_Gamma.

The data come from an exact displacement written as sympy expressions (cf.Exact): f = -div sigma(u)
is derived, not typed.  CG with the geometric multigrid solves it (three copies of the scalar
hierarchy).  Without boundary conditions the rigid motions a + b x x would be its kernel.

Run it: python docs/examples/elasticity.py   (L2 rate about 2, H1 about 1).
"""

import cutfem as cf

U = cf.Exact(["sin(x) * exp(y / 2)", "cos(y) * z", "x * y * z + sin(z)"])  # the exact displacement
GRAD_U = U.grad                                                                # (grad u)_ij = d u_i / d x_j


def main(spacing=0.2, mu=1.0, lam=2.0, gamma=10.0, gamma_g=0.1):
    """L2 and H1 errors of the displacement at one background spacing, and the CG iterations."""
    cut = cf.cut_mesh(cf.structured_box([-1.2] * 3, [1.2] * 3, spacing=spacing), cf.Sphere(1.0))
    W = cf.VectorSpace(cf.CutSpace(cut, cf.NEG))     # [P1]^3 on every tet that meets the ball
    dx, ds = cut.dx(cf.NEG), cut.ds()
    dg = cut.dF(cut.ghost_facets(cf.NEG))

    sigma = 2 * mu * U.sym_grad + lam * U.div * cf.Exact.identity()
    f = -sigma.div                                       # the load, exact in sympy
    N = cf.elasticity_nitsche(ds, mu, lam, gamma, g=U)   # u = U on Gamma; N.load its right-hand side
    a = cf.elasticity(dx, mu, lam) + N + (2 * mu + lam) * gamma_g * cf.face_jump_penalty(dg, h_power=1)
    K = cf.assemble(a, W)
    b = cf.assemble(cf.load(f, dx) + N.load, W)
    u, info = cf.solve(K, b, space=W, indefinite_hint=a.indefinite_hint)
    l2, h1 = cf.l2_h1_errors(W, u, lambda x: (U(x), GRAD_U(x)), dx)
    return {"h": W.h, "dofs": W.n_dofs, "l2": l2, "h1": h1, "iterations": info.iterations}


if __name__ == "__main__":
    runs = [main(s) for s in (0.2, 0.1, 0.05)]
    h = [r["h"] for r in runs]
    l2_rates, h1_rates = cf.rates(h, [r["l2"] for r in runs]), cf.rates(h, [r["h1"] for r in runs])
    print(f"{'h':>8} {'dofs':>7} {'L2 error':>10} {'rate':>5} {'H1 error':>10} {'rate':>5} {'CG':>3}")
    for i, r in enumerate(runs):
        a, b = ("", "") if i == 0 else (f"{l2_rates[i - 1]:.2f}", f"{h1_rates[i - 1]:.2f}")
        print(f"{r['h']:8.4f} {r['dofs']:7d} {r['l2']:10.3e} {a:>5} {r['h1']:10.3e} {b:>5} {r['iterations']:3d}")
