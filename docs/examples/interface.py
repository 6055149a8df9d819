"""The interface problem (Hansbo-Hansbo): a jump of the coefficient across a sphere.

    -div(a grad u) = f in the box,  a = a_in inside the sphere |x| = R, a_out outside,
    [u] = 0 and [a n.grad u] = 0 across it,  u = u_exact on the box's boundary.

Each side has its own P1 field on the tets that meet it (a cut tet carries both), glued by
Nitsche's method on the interface with harmonic weights, and a ghost penalty on each side keeps
the system well conditioned however the sphere cuts.  Exact solution: with psi = |x|^2 - R^2 and
w = sin(x) exp(y/2) + 2, u = psi w / a on each side: psi = 0 on the sphere makes u continuous and
a grad u = grad(psi w) makes the flux continuous; f = -Lap(psi w) = -(6 w + 4 x.grad w + psi Lap w).

Run it: python docs/examples/interface.py   (L2 rates about 2, H1 about 1 on both sides).
"""

import numpy as np

import cutfem as cf

R = 0.8


def psi_w(x):
    """psi w, its gradient and f = -Lap(psi w) at points x (..., 3)."""
    e = np.sin(x[..., 0]) * np.exp(x[..., 1] / 2)
    w = e + 2
    grad_w = np.stack([np.cos(x[..., 0]) * np.exp(x[..., 1] / 2), 0.5 * e, 0 * e], axis=-1)
    psi = (x**2).sum(-1) - R**2
    grad = psi[..., None] * grad_w + 2 * x * w[..., None]
    f = -(6 * w + 4 * (x * grad_w).sum(-1) + psi * (-0.75 * e))
    return psi * w, grad, f


def main(spacing=0.2, a_in=1.0, a_out=10.0, gamma=10.0, gamma_g=0.1):
    """L2 and H1 errors on each side at one background spacing."""
    cut = cf.cut_mesh(cf.structured_box([-1.2] * 3, [1.2] * 3, spacing=spacing), cf.Sphere(R))
    W = cf.ProductSpace(cf.CutSpace(cut, cf.NEG), cf.CutSpace(cut, cf.POS))  # field 0 inside, 1 outside
    a = {cf.NEG: a_in, cf.POS: a_out}

    # the interface terms couple the two fields; each side adds its stiffness, ghost penalty and load
    form = cf.interface_nitsche(cut.ds(), a_in, a_out, gamma, "harmonic")
    rhs = 0
    for k, side in enumerate((cf.NEG, cf.POS)):
        form = form + a[side] * cf.stiffness(cut.dx(side), field=k)
        form = form + a[side] * gamma_g * cf.face_jump_penalty(cut.dF(cut.ghost_facets(side)), h_power=1, field=k)
        rhs = rhs + cf.load(lambda x: psi_w(x)[2], cut.dx(side), field=k)
    K, b = cf.assemble(form, W), cf.assemble(rhs, W)

    # Dirichlet values on the box's boundary, which only the outside field reaches
    outer = W[1]
    nodes = outer.boundary_dofs
    K, b = cf.apply_dirichlet(K, b, W.offsets[1] + nodes, psi_w(outer.dof_points[nodes])[0] / a_out)
    x, info = cf.solve(K, b, space=W)

    errors = {"h": W.h, "dofs": W.n_dofs}
    for k, (name, side, u) in enumerate(zip(("in", "out"), (cf.NEG, cf.POS), W.split(x))):
        def exact(p, a_side=a[side]):  # (u, grad u) = (psi w, grad(psi w)) / a on this side
            value, grad, _ = psi_w(p)
            return value / a_side, grad / a_side

        errors[f"l2_{name}"], errors[f"h1_{name}"] = cf.l2_h1_errors(W[k], u, exact, cut.dx(side))
    return errors


if __name__ == "__main__":
    runs = [main(s) for s in (0.2, 0.1, 0.05)]
    h = [r["h"] for r in runs]
    keys = ("l2_in", "h1_in", "l2_out", "h1_out")
    r8 = {k: cf.rates(h, [r[k] for r in runs]) for k in keys}
    print(f"{'h':>8} {'dofs':>7}" + "".join(f" {k:>10} {'rate':>5}" for k in keys))
    for i, r in enumerate(runs):
        cells = "".join(f" {r[k]:10.3e} {'' if i == 0 else f'{r8[k][i - 1]:.2f}':>5}" for k in keys)
        print(f"{r['h']:8.4f} {r['dofs']:7d}{cells}")
