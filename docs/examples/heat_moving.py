"""A moving domain: the heat equation in a translating ball, Eulerian BDF2 on a fixed mesh.

    u_t - Lap u = f in Omega(t) = {|x - c(t)| < 1/2},  c(t) = (-1/4 + t/2, 0, 0),  u = g on its boundary.

Each step solves on the domain of the new time, with the unknown on the tets of a slightly larger
domain {phi < delta} (cf.ActiveDomain): delta covers how far the boundary moves in the two steps
BDF2 looks back (cf.strip_width), so the earlier solutions, carried to the new tets by their nodal
values (cf.transfer), are defined wherever the new domain reads them.  A ghost penalty on the facets
of that strip extends each solution past the boundary (Lehrenfeld and Olshanskii, M2AN 2019).

Exact solution u = exp(-t) w(x), w from sympy (cf.Exact), so f = exp(-t) (-w - Lap w).

Run it: python docs/examples/heat_moving.py   (L2 rate about 2 with dt = h / 2).
"""

import numpy as np

import cutfem as cf

w = cf.Exact("cos(x) * sin(y + 1/2) * exp(z/2)")
f = -w - w.laplacian
speed, T = np.array([0.5, 0.0, 0.0]), 0.5


def ball(t):
    return cf.Sphere(0.5, np.array([-0.25, 0.0, 0.0]) + speed * t)


def main(spacing=0.2, gamma=20.0, gamma_g=0.1):
    """The L2 error at the final time, BDF2 with dt = spacing / 2 (its first step BDF1)."""
    background = cf.structured_box([-1.25] * 3, [1.25] * 3, spacing=spacing)
    steps = int(np.ceil(T / (spacing / 2)))
    dt = T / steps
    delta = cf.strip_width(np.linalg.norm(speed), dt, order=2)
    domain = cf.ActiveDomain(background, ball(0.0), delta)
    history = [(domain.space.interpolate(w), domain.space)]        # u^0 and its space
    for n in range(1, steps + 1):                                   # a loop over time steps
        t = n * dt
        domain = cf.ActiveDomain(background, ball(t), delta)
        V, dx = domain.space, domain.dx
        a0, weights = (1.0, [1.0]) if n == 1 else (1.5, [2.0, -0.5])   # BDF1, then BDF2
        N = cf.nitsche(domain.ds, gamma, g=lambda x: np.exp(-t) * w(x))
        a = (a0 / dt) * cf.mass(dx) + cf.stiffness(dx) + N \
            + gamma_g * cf.face_jump_penalty(domain.dF, h_power=1) + (gamma_g / dt) * cf.face_jump_penalty(domain.dF, h_power=3)
        earlier = sum(c * cf.transfer(u, old, V, over=dx) for c, (u, old) in zip(weights, reversed(history)))
        b = cf.assemble(cf.load(lambda x: np.exp(-t) * f(x), dx) + N.load, V) + cf.assemble(cf.mass(dx), V) @ earlier / dt
        u, info = cf.solve(cf.assemble(a, V), b, space=V)
        history = (history + [(u, V)])[-2:]
    return {"h": V.h, "dofs": V.n_dofs, "steps": steps, "l2": cf.l2_error(V, u, lambda x: np.exp(-T) * w(x), domain.dx)}


if __name__ == "__main__":
    runs = [main(s) for s in (0.2, 0.1, 0.05)]
    l2_rates = cf.rates([r["h"] for r in runs], [r["l2"] for r in runs])
    print(f"{'h':>8} {'dofs':>7} {'steps':>6} {'L2 error':>10} {'rate':>5}")
    for i, r in enumerate(runs):
        rate = "" if i == 0 else f"{l2_rates[i - 1]:.2f}"
        print(f"{r['h']:8.4f} {r['dofs']:7d} {r['steps']:6d} {r['l2']:10.3e} {rate:>5}")
