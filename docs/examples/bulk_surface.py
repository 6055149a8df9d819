"""Coupled bulk-surface diffusion (Burman-Hansbo-Larson-Zahedi): a ball and its sphere exchange mass.

    -Lap u_B + u_B = f_B in the ball |x| < 1,         n.grad u_B = b_S u_S - b_B u_B on the sphere,
    -Lap_S u_S + b_S u_S - b_B u_B = f_S on the sphere.

The bulk field lives on the tets that meet the ball (CutFEM, ghost penalty), the surface field on
the cut tets (TraceFEM, normal-gradient stabilization); one product space holds both.  Multiplying
the bulk equation by b_B and the surface one by b_S makes the form symmetric:

    b_B (grad u_B, grad v_B) + b_B (u_B, v_B) + b_S (grad_S u_S, grad_S v_S)
    + (b_S u_S - b_B u_B, b_S v_S - b_B v_B)_Gamma + stabilizations = b_B (f_B, v_B) + b_S (f_S, v_S)_Gamma.

Exact solution: u_B = exp(d.x), and u_S from the coupling condition, U_S = F(d.p) at the closest
point p = x/|x| with F(s) = e^s (s + b_B) / b_S (on the unit sphere n.grad u_B = (d.x) u_B).

Run it: python docs/examples/bulk_surface.py   (L2 rates about 2 for both fields).
"""

import numpy as np

import cutfem as cf

D = np.array([0.6, 0.3, -0.4])
B_BULK, B_SURF = 1.0, 2.0


def u_bulk(x):
    return np.exp(x @ D)


def grad_bulk(x):
    return u_bulk(x)[..., None] * D


def F(s):
    """F, F' and F'' of the surface solution's profile."""
    e = np.exp(s)
    return e * (s + B_BULK) / B_SURF, e * (s + B_BULK + 1) / B_SURF, e * (s + B_BULK + 2) / B_SURF


def closest(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def u_surface(x):
    return F(closest(x) @ D)[0]


def grad_surface(x):  # its tangential part is the surface gradient (the error takes that part)
    return F(closest(x) @ D)[1][..., None] * D


def f_bulk(x):
    return (1 - D @ D) * u_bulk(x)


def f_surface(x):
    s = closest(x) @ D  # on the unit sphere d.n = d.p = s, and Lap_S U = F''(|d|^2 - s^2) - 2 F' s
    U, U1, U2 = F(s)
    return -(U2 * (D @ D - s**2) - 2 * U1 * s) + B_SURF * U - B_BULK * np.exp(s)


@cf.bilinear_form(symmetric=True)
def exchange(u, v, w):  # u[0], u[1]: the product space's fields (bulk, surface)
    return (B_SURF * u[1] - B_BULK * u[0]) * (B_SURF * v[1] - B_BULK * v[0])


def main(spacing=0.2, gamma_g=0.1, tau_n=1.0):
    """L2 errors of both fields and the H1 error of the bulk field at one background spacing."""
    cut = cf.cut_mesh(cf.structured_box([-1.1] * 3, [1.1] * 3, spacing=spacing), cf.Sphere(1.0))
    W = cf.ProductSpace(bulk=cf.CutSpace(cut, cf.NEG), surface=cf.CutSpace(cut, cf.CUT))
    dx, ds = cut.dx(cf.NEG), cut.ds()
    form = (
        B_BULK * cf.stiffness(dx, field="bulk") + B_BULK * cf.mass(dx, field="bulk")
        + B_SURF * cf.tangential_stiffness(ds, field="surface")
        + exchange * ds
        + B_BULK * gamma_g * cf.face_jump_penalty(cut.dF(cut.ghost_facets(cf.NEG)), h_power=1, field="bulk")
        + B_SURF * tau_n * cf.normal_gradient_penalty(cut.dx(cf.CUT), h_power=-1, field="surface")
    )
    rhs = B_BULK * cf.load(f_bulk, dx, field="bulk") + B_SURF * cf.load(f_surface, ds, field="surface")
    x, info = cf.solve(cf.assemble(form, W), cf.assemble(rhs, W), space=W)
    ub, us = W.split(x)
    return {
        "h": W.h,
        "dofs": W.n_dofs,
        "l2_bulk": cf.l2_error(W["bulk"], ub, u_bulk, dx),
        "h1_bulk": cf.h1_error(W["bulk"], ub, grad_bulk, dx),
        "l2_surface": cf.l2_error(W["surface"], us, u_surface),
        "h1_surface": cf.h1_error(W["surface"], us, grad_surface),
    }


if __name__ == "__main__":
    runs = [main(s) for s in (0.2, 0.1, 0.05)]
    h = [r["h"] for r in runs]
    keys = ("l2_bulk", "h1_bulk", "l2_surface", "h1_surface")
    r8 = {k: cf.rates(h, [r[k] for r in runs]) for k in keys}
    print(f"{'h':>8} {'dofs':>7}" + "".join(f" {k:>10} {'rate':>5}" for k in keys))
    for i, r in enumerate(runs):
        cells = "".join(f" {r[k]:10.3e} {'' if i == 0 else f'{r8[k][i - 1]:.2f}':>5}" for k in keys)
        print(f"{r['h']:8.4f} {r['dofs']:7d}{cells}")
