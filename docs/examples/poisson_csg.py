"""Poisson in a ball cut by a plane: Dirichlet on the sphere, Neumann on the flat disc.

    -Lap u = f in Omega = {|x| < 1} and {z < 1/2},   u = g on the sphere part,   n.grad u = g_N on the disc.

Omega has an edge where its two boundary parts meet.  It is the intersection of the insides of two
level sets, a ball and a half-space, cut at once (cf.intersection); each part of its boundary is a
measure of its own, cut.ds(ball) and cut.ds(cap), whose triangles carry their outward normal w.n.
The exact solution comes from sympy (cf.Exact): f = -Lap u, g = u, and g_N = grad u . (0, 0, 1),
the disc's outward normal (exact: a P1 cut reproduces a plane).  The forms:

    a(u, v) = (grad u, grad v)_Omega_h - (n.grad u, v)_S - (u, n.grad v)_S + gamma/h (u, v)_S + ghost penalty,
    l(v)    = (f, v)_Omega_h + (g, gamma/h v - n.grad v)_S + (g_N, v)_D,      S the sphere part, D the disc.

Run it: python docs/examples/poisson_csg.py   (L2 rate about 2, H1 about 1).
"""

import numpy as np

import cutfem as cf

u = cf.Exact("sin(pi*x/2)*cos(pi*y/3)*exp(z/2)")
f = -u.laplacian
g_n = u.grad.dot(cf.Exact([0, 0, 1]))  # the flux through the disc


@cf.bilinear_form(symmetric=True)
def nitsche(uh, v, w):
    return -cf.dot(w.n, uh.grad) * v - cf.dot(w.n, v.grad) * uh + w.gamma / w.h * uh * v


@cf.linear_form
def nitsche_rhs(v, w):
    return w.at(u) * (w.gamma / w.h * v - cf.dot(w.n, v.grad))


def main(spacing=0.2, gamma=10.0, gamma_g=0.1):
    """L2 and H1 errors of u_h over Omega_h at one background spacing."""
    ball, cap = cf.Sphere(1.0), cf.Plane((0, 0, 1), (0, 0, 0.5))
    cut = cf.cut_mesh(cf.structured_box([-1.2] * 3, [1.2] * 3, spacing=spacing), cf.intersection(ball, cap))
    V = cf.CutSpace(cut, cf.NEG)                     # P1 on every tet that meets Omega
    dx, sphere, disc = cut.dx(cf.NEG), cut.ds(ball), cut.ds(cap)
    ghost = cut.dF(cut.ghost_facets(cf.NEG))
    K = cf.assemble(cf.stiffness(dx) + nitsche.on(sphere, gamma=gamma) + gamma_g * cf.face_jump_penalty(ghost, h_power=1), V)
    b = cf.assemble(cf.load(f, dx) + nitsche_rhs.on(sphere, gamma=gamma) + cf.load(g_n, disc), V)
    uh, info = cf.solve(K, b, space=V)
    l2, h1 = cf.l2_h1_errors(V, uh, lambda x: (u(x), u.grad(x)), dx)
    return {"h": V.h, "dofs": V.n_dofs, "l2": l2, "h1": h1, "volume": dx.size, "disc": disc.size}


if __name__ == "__main__":
    runs = [main(s) for s in (0.4, 0.2, 0.1)]
    h = [r["h"] for r in runs]
    l2_rates, h1_rates = cf.rates(h, [r["l2"] for r in runs]), cf.rates(h, [r["h1"] for r in runs])
    print(f"{'h':>8} {'dofs':>7} {'L2 error':>10} {'rate':>5} {'H1 error':>10} {'rate':>5}")
    for i, r in enumerate(runs):
        a, c = ("", "") if i == 0 else (f"{l2_rates[i - 1]:.2f}", f"{h1_rates[i - 1]:.2f}")
        print(f"{r['h']:8.4f} {r['dofs']:7d} {r['l2']:10.3e} {a:>5} {r['h1']:10.3e} {c:>5}")
    print(f"disc area {runs[-1]['disc']:.4f} (exact {0.75 * np.pi:.4f}), volume {runs[-1]['volume']:.4f} "
          f"(exact {4 / 3 * np.pi - np.pi * 0.25 * 2.5 / 3:.4f})")
