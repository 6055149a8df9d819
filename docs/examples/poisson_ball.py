"""Fictitious-domain Poisson in the unit ball: symmetric Nitsche and a ghost penalty.

    -Lap u = f in Omega = {|x| < 1},   u = g on its boundary Gamma,

solved on the tetrahedra of a box that meet the ball (Burman-Hansbo).  The exact solution is
u = sin(x) exp(y/2), so f = 3u/4 and g = u on Gamma.  The form, written as user integrands:

    a(u, v) = (grad u, grad v)_Omega_h - (n.grad u, v)_Gamma_h - (u, n.grad v)_Gamma_h + gamma/h (u, v)_Gamma_h
              + gamma_g h (jump of n_F.grad u, jump of n_F.grad v)_ghost faces,
    l(v)    = (f, v)_Omega_h + (g, gamma/h v - n.grad v)_Gamma_h.

Run it: python docs/examples/poisson_ball.py   (L2 rate about 2, H1 about 1).
"""

import numpy as np

import cutfem as cf


def u_exact(x):
    return np.sin(x[..., 0]) * np.exp(x[..., 1] / 2)


def grad_exact(x):
    e = np.exp(x[..., 1] / 2)
    return np.stack([np.cos(x[..., 0]) * e, 0.5 * np.sin(x[..., 0]) * e, 0 * e], axis=-1)


# One integrand serves the volume and the boundary: a volume measure has no normal (w.n is None).
# w.n is the normal of Gamma_h out of the domain, w.h the local mesh size, w.gamma a parameter
# passed to assemble by keyword.
@cf.bilinear_form(symmetric=True)
def poisson(u, v, w):
    if w.n is None:
        return cf.dot(u.grad, v.grad)
    return -cf.dot(w.n, u.grad) * v - cf.dot(w.n, v.grad) * u + w.gamma / w.h * u * v


@cf.linear_form
def rhs(v, w):
    if w.n is None:
        return 0.75 * w.at(u_exact) * v  # f = 3u/4 at the quadrature points
    return w.at(u_exact) * (w.gamma / w.h * v - cf.dot(w.n, v.grad))


def main(spacing=0.2, gamma=10.0, gamma_g=0.1):
    """L2 and H1 errors of u_h over the cut ball Omega_h at one background spacing."""
    background = cf.structured_box([-1.2] * 3, [1.2] * 3, spacing=spacing)
    cut = cf.cut_mesh(background, cf.Sphere(1.0))
    V = cf.CutSpace(cut, cf.NEG)                     # P1 on every tet that meets the ball
    dx, ds = cut.dx(cf.NEG), cut.ds()                  # Omega_h and Gamma_h with their quadrature
    dg = cut.dF(cut.ghost_facets(cf.NEG))              # the faces of cut tets inside the active mesh
    K = cf.assemble(poisson * dx + poisson * ds + gamma_g * cf.face_jump_penalty(dg, h_power=1), V, gamma=gamma)
    b = cf.assemble(rhs * dx + rhs * ds, V, gamma=gamma)
    u, info = cf.solve(K, b, space=V)
    l2, h1 = cf.l2_h1_errors(V, u, lambda x: (u_exact(x), grad_exact(x)), dx)
    return {"h": V.h, "dofs": V.n_dofs, "l2": l2, "h1": h1}


if __name__ == "__main__":
    runs = [main(s) for s in (0.4, 0.2, 0.1)]
    h = [r["h"] for r in runs]
    l2_rates, h1_rates = cf.rates(h, [r["l2"] for r in runs]), cf.rates(h, [r["h1"] for r in runs])
    print(f"{'h':>8} {'dofs':>7} {'L2 error':>10} {'rate':>5} {'H1 error':>10} {'rate':>5}")
    for i, r in enumerate(runs):
        a, b = ("", "") if i == 0 else (f"{l2_rates[i - 1]:.2f}", f"{h1_rates[i - 1]:.2f}")
        print(f"{r['h']:8.4f} {r['dofs']:7d} {r['l2']:10.3e} {a:>5} {r['h1']:10.3e} {b:>5}")
