"""Stokes flow in a ball: equal-order P1-P1 on a cut mesh, solved by block-preconditioned MINRES.

    -Lap u + grad p = f,  div u = 0 in the unit ball,  u = g on its sphere.

One product space holds the velocity (a vector field), the pressure and a multiplier for the
pressure's mean; ``cf.divergence(dx, by_parts=True)`` couples velocity and pressure,
(v, grad p) = -(div v, p) + (v . n, p) on the boundary, and ``cf.mean_constraint`` the pressure
and its multiplier.  Nitsche imposes u = g on the cut boundary; ghost penalties on the faces of
the cut tets (velocity h, pressure h^3) and the Brezzi-Pitkaranta term -beta h^2 (grad p, grad q)
(``cf.stiffness(dx, h_power=2)``) stabilize the equal-order pair.  The system is symmetric indefinite: ``cf.solve`` with ``primal``
and ``schur`` runs MINRES, preconditioned by multigrid on the velocity block and on the Schur
approximation M_p + the pressure's stabilization (docs/math.md §12).

Exact solution from sympy: u = curl A (divergence free), p = x y z + x^2 - y^2.

Run it: python docs/examples/stokes.py   (L2 rates about 2 for u, H1 1, pressure >= 1).
"""

import cutfem as cf

U = cf.Exact(["sin(y)*sin(z)", "sin(z)*sin(x)", "sin(x)*sin(y)"]).curl
P = cf.Exact("x*y*z + x**2 - y**2")
F = -U.laplacian + P.grad
BETA, GAMMA = 0.05, 20.0


@cf.linear_form
def normal_data(v, w):  # (g . n, q) on the boundary
    return cf.dot(w.at(U), w.n) * v[1]


def main(spacing=0.2):
    """The velocity's L2 and H1 errors and the pressure's L2 error, at one spacing."""
    cut = cf.cut_mesh(cf.structured_box([-1.1] * 3, [1.1] * 3, spacing=spacing), cf.Sphere(1.0))
    V = cf.CutSpace(cut, cf.NEG)
    W = cf.ProductSpace(u=cf.VectorSpace(V), p=V, mean=cf.RealSpace())
    dx, ds, dg = cut.dx(cf.NEG), cut.ds(), cut.dF(cut.ghost_facets(cf.NEG))
    N = cf.nitsche(ds, GAMMA, g=U, field="u")
    a = cf.stiffness(dx, field="u") + N + cf.divergence(dx, by_parts=True) + cf.mean_constraint(dx) \
        - BETA * cf.stiffness(dx, field="p", h_power=2) \
        + 0.1 * cf.face_jump_penalty(dg, h_power=1, field="u") - 0.1 * cf.face_jump_penalty(dg, h_power=3, field="p")
    b = cf.assemble(cf.load(F, dx, field="u") + N.load + normal_data * ds, W)
    S = cf.assemble(cf.mass(dx) + BETA * cf.stiffness(dx, h_power=2) + 0.1 * cf.face_jump_penalty(dg, h_power=3), V)
    x, info = cf.solve(cf.assemble(a, W), b, space=W, primal="u", schur={"p": S})
    u, p, _ = W.split(x)
    return {"h": V.h, "dofs": W.n_dofs, "iterations": info.iterations,
            "l2_u": cf.l2_error(V, W["u"].nodal(u), U, dx),
            "h1_u": cf.h1_error(V, W["u"].nodal(u), U.grad, dx),
            "l2_p": cf.l2_error(V, p, P, dx)}  # P has mean zero over the ball


if __name__ == "__main__":
    runs = [main(s) for s in (0.2, 0.1, 0.05)]
    print(f"{'h':>8} {'dofs':>7} {'its':>4} {'L2 u':>10} {'H1 u':>10} {'L2 p':>10}")
    for r in runs:
        print(f"{r['h']:8.4f} {r['dofs']:7d} {r['iterations']:4d} {r['l2_u']:10.3e} {r['h1_u']:10.3e} {r['l2_p']:10.3e}")
    for key in ("l2_u", "h1_u", "l2_p"):
        print(key, "rates", [f"{x:.2f}" for x in cf.rates([r["h"] for r in runs], [r[key] for r in runs])])
