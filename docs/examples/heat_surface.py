"""A time-dependent problem: the heat equation on a cut sphere, TraceFEM in space, theta-scheme in time.

    u_t - Lap_S u = f on the unit sphere S, 0 < t <= T,   u(0) = u_0.

In space: the trace of P1 on the cut tets, with the normal-gradient stabilization
s_a(u, v) = sum_T h^a (n_h.grad u, n_h.grad v)_T added to the mass (a = 1) and to the stiffness
(a = -1), so both matrices are well conditioned however the sphere cuts.  In time, the theta-scheme:

    (M + theta dt A) u^n = (M - (1 - theta) dt A) u^(n-1) + dt (theta F^n + (1 - theta) F^(n-1)).

theta = 1 is backward Euler, taken with dt = h^2; theta = 1/2 is Crank-Nicolson, with dt = h: both
O(h^2) in L2.  The matrix is the same at every step, so it is factorized once (DirectSolver).

Exact solution: u = exp(-t) exp(d.p) at the closest point p = x/|x|, so f = exp(-t) g with
g = -(U + Lap_S U), U = exp(d.p), Lap_S U = U (|d|^2 - (d.p)^2) - 2 (d.p) U on the unit sphere.

Run it: python docs/examples/heat_surface.py   (L2 rate about 2 for either scheme).
"""

import numpy as np

import cutfem as cf

D = np.array([0.6, 0.3, -0.4])


def on_sphere(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def u_exact(t):
    return lambda x: np.exp(-t) * np.exp(on_sphere(x) @ D)


def g(x):  # f(x, t) = exp(-t) g(x): the load is exp(-t_n) G with G assembled once
    s = on_sphere(x) @ D
    U = np.exp(s)
    return -(U + U * (D @ D - s**2 - 2 * s))


def main(spacing=0.2, theta=1.0, final_time=0.5, tau_n=1.0):
    """The L2 error on S_h at the final time, at one background spacing."""
    cut = cf.cut_mesh(cf.structured_box([-1.1] * 3, [1.1] * 3, spacing=spacing), cf.Sphere(1.0))
    V = cf.CutSpace(cut, cf.CUT)
    ds, dT = cut.ds(), cut.dx(cf.CUT)
    M = cf.assemble(cf.mass(ds) + tau_n * cf.normal_gradient_penalty(dT, h_power=1), V)
    A = cf.assemble(cf.tangential_stiffness(ds) + tau_n * cf.normal_gradient_penalty(dT, h_power=-1), V)
    G = cf.assemble(cf.load(g, ds), V)

    dt_max = spacing**2 if theta == 1.0 else spacing
    steps = int(np.ceil(final_time / dt_max - 1e-9))     # uniform steps of dt <= dt_max ending at T
    dt = final_time / steps
    step = cf.DirectSolver((M + theta * dt * A).tocsr())   # one factorization for all steps
    explicit = (M - (1 - theta) * dt * A).tocsr()
    u = u_exact(0.0)(V.dof_points)                          # u_0: the nodal interpolant
    for n in range(1, steps + 1):                           # a loop over time steps, not elements
        weight = dt * (theta * np.exp(-n * dt) + (1 - theta) * np.exp(-(n - 1) * dt))
        u = step.solve(explicit @ u + weight * G)
    return {"h": V.h, "dofs": V.n_dofs, "steps": steps, "l2": cf.l2_error(V, u, u_exact(final_time))}


if __name__ == "__main__":
    for theta, name in ((1.0, "backward Euler, dt = h^2"), (0.5, "Crank-Nicolson, dt = h")):
        runs = [main(s, theta) for s in (0.2, 0.1, 0.05)]
        l2_rates = cf.rates([r["h"] for r in runs], [r["l2"] for r in runs])
        print(f"{name}\n{'h':>8} {'dofs':>7} {'steps':>6} {'L2 error':>10} {'rate':>5}")
        for i, r in enumerate(runs):
            rate = "" if i == 0 else f"{l2_rates[i - 1]:.2f}"
            print(f"{r['h']:8.4f} {r['dofs']:7d} {r['steps']:6d} {r['l2']:10.3e} {rate:>5}")
