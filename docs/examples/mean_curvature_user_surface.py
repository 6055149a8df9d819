"""The mean curvature vector of a surface you define: any smooth level set, written as a function.

On a closed surface S, the mean curvature vector is H = -Lap_S x (H = (k1 + k2) n, n outward; a
sphere of radius R has H = (2/R) n).  Multiplying by a test function and integrating by parts on
the cut surface S_h gives a mass-matrix problem, one right-hand side per coordinate:

    (H_h, v)_Sh + tau_F (jump of n_F.grad H_h, jump of n_F.grad v)_faces = (grad_Sh x, grad_Sh v)_Sh.

The surface here is a quartic, phi = x^4 + y^4 + z^4 - 1 (a rounded cube), given as plain numpy
callables.  cutfem knows nothing else about it: FunctionLevelSet finds the closest point p(x) on
the exact surface by Newton's method and the exact H at p from grad phi and Hess phi, so the error
of H_h is measured against the smooth surface.  (Without gradient/hessian it takes central
differences; FunctionLevelSet.from_expression("x**4 + y**4 + z**4 - 1") reads the same surface
from text.)

Run it: python docs/examples/mean_curvature_user_surface.py   (L2 rate about 0.8 at these spacings,
on the way to the method's O(h): the curvature varies fast near the rounded edges; a sphere shows
rates near 2.)
"""

import numpy as np

import cutfem as cf


def phi(x):
    return (x**4).sum(-1) - 1


def grad_phi(x):
    return 4 * x**3


def hess_phi(x):
    return 12 * x[..., :, None] ** 2 * np.eye(3)  # diagonal: d2 phi / dx_i^2 = 12 x_i^2


# |grad phi| <= 4 * sqrt(3) * 1.2**3 in the box below: a true bound lets the cut skip far cells
surface = cf.FunctionLevelSet(phi, gradient=grad_phi, hessian=hess_phi, lipschitz=4 * 3**0.5 * 1.2**3,
                              bounds=([-1.0] * 3, [1.0] * 3), name="x^4 + y^4 + z^4 = 1")


def main(spacing=0.2, tau_f=0.1):
    """The L2 error of H_h on S_h against the exact H at the closest points, at one spacing."""
    cut = cf.cut_mesh(cf.structured_box([-1.2] * 3, [1.2] * 3, spacing=spacing), surface)
    V = cf.CutSpace(cut, cf.CUT)
    ds, faces = cut.ds(), cut.dF(cut.interior_facets(cf.CUT))
    K = cf.assemble(cf.mass(ds) + tau_f * cf.face_jump_penalty(faces), V)
    H, info = cf.solve(K, cf.assemble(cf.position_load(ds), V), space=V)  # (n, 3): one matrix, three loads
    return {"h": V.h, "dofs": V.n_dofs, "area": cut.area, "l2": cf.l2_error(V, H, surface.exact_mean_curvature_vector)}


if __name__ == "__main__":
    runs = [main(s) for s in (0.2, 0.1, 0.05)]
    h = [r["h"] for r in runs]
    l2_rates = cf.rates(h, [r["l2"] for r in runs])
    print(f"{'h':>8} {'dofs':>7} {'area':>8} {'L2 error':>10} {'rate':>5}")
    for i, r in enumerate(runs):
        rate = "" if i == 0 else f"{l2_rates[i - 1]:.2f}"
        print(f"{r['h']:8.4f} {r['dofs']:7d} {r['area']:8.4f} {r['l2']:10.3e} {rate:>5}")
