"""TraceFEM: the Laplace-Beltrami equation on a sphere cut from a background mesh.

    -Lap_S u + u = f on the unit sphere S.

No surface mesh is built: the level set |x| - 1 cuts the background tets, S_h is the piecewise
planar surface it leaves, and the space is the trace on S_h of P1 on the cut tets.  Those traces
can be nearly zero on a tet barely touched by S_h, so a face penalty (jumps of the gradient across
the faces of the cut tets) makes the system well conditioned however the surface cuts:

    (grad_Sh u, grad_Sh v)_Sh + (u, v)_Sh + tau_F (jump of n_F.grad u, jump of n_F.grad v)_faces = (f^e, v)_Sh.

Exact solution: u = x y + z (spherical harmonics of degree 2 and 1, so -Lap_S u = 6 x y + 2 z and
f = 7 x y + 3 z), extended constantly along the normals: every function is read at the closest
point p = x / |x|.

Run it: python docs/examples/laplace_beltrami.py   (L2 rate about 2, H1 about 1).
"""

import numpy as np

import cutfem as cf


def on_sphere(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def u_exact(x):
    p = on_sphere(x)
    return p[..., 0] * p[..., 1] + p[..., 2]


def f(x):
    p = on_sphere(x)
    return 7 * p[..., 0] * p[..., 1] + 3 * p[..., 2]


def grad_exact(x):  # grad_S u = P grad u at p, P = I - n n^T
    p = on_sphere(x)
    g = np.stack([p[..., 1], p[..., 0], np.ones_like(p[..., 0])], axis=-1)
    return g - (g * p).sum(-1, keepdims=True) * p


def main(spacing=0.2, tau_f=0.1):
    """L2 and H1 errors on S_h at one background spacing."""
    cut = cf.cut_mesh(cf.structured_box([-1.1] * 3, [1.1] * 3, spacing=spacing), cf.Sphere(1.0))
    V = cf.CutSpace(cut, cf.CUT)                      # P1 on the cut tets: traces on S_h
    ds = cut.ds()                                       # S_h with its quadrature
    faces = cut.dF(cut.interior_facets(cf.CUT))         # faces shared by two cut tets
    K = cf.assemble(cf.tangential_stiffness(ds) + cf.mass(ds) + tau_f * cf.face_jump_penalty(faces), V)
    u, info = cf.solve(K, cf.assemble(cf.load(f, ds), V), space=V)
    return {"h": V.h, "dofs": V.n_dofs, "l2": cf.l2_error(V, u, u_exact), "h1": cf.h1_error(V, u, grad_exact)}


if __name__ == "__main__":
    runs = [main(s) for s in (0.2, 0.1, 0.05)]
    h = [r["h"] for r in runs]
    l2_rates, h1_rates = cf.rates(h, [r["l2"] for r in runs]), cf.rates(h, [r["h1"] for r in runs])
    print(f"{'h':>8} {'dofs':>7} {'L2 error':>10} {'rate':>5} {'H1 error':>10} {'rate':>5}")
    for i, r in enumerate(runs):
        a, b = ("", "") if i == 0 else (f"{l2_rates[i - 1]:.2f}", f"{h1_rates[i - 1]:.2f}")
        print(f"{r['h']:8.4f} {r['dofs']:7d} {r['l2']:10.3e} {a:>5} {r['h1']:10.3e} {b:>5}")
