"""The multigrid on P2 fields (docs/math.md §20): the hierarchy augmented by several nodal vectors
(an exact identity), and CG iterations of the order-2 problems at most 40 and flat under refinement
(coarse levels in the fast suite, three levels in the slow one)."""

import numpy as np
import pytest
import scipy.sparse as sp

import cutfem
from cutfem.solvers.multigrid import GeometricMultigrid, augmented_hierarchy, kuhn_prolongation, lattice_hierarchy


def _lattice(m=9):
    g = np.arange(m)
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)


def test_augmented_hierarchy_with_two_vectors():
    """w (n, 2): [P_0, diag(w_1) P_0, diag(w_2) P_0], then diag(P_1, P_1, P_1): level 2 holds
    P_0 P_1 v + w_1 P_0 P_1 v' + w_2 P_0 P_1 v''; one vector (n,) is the same as (n, 1)."""
    ijk = _lattice()
    rng = np.random.default_rng(3)
    w = rng.normal(size=(len(ijk), 2))
    P0, c1 = kuhn_prolongation(ijk)
    P1, _ = kuhn_prolongation(c1)
    h = augmented_hierarchy(lattice_hierarchy(ijk), w)
    Q0, Q1 = next(h), next(h)
    assert Q0.shape == (len(ijk), 3 * P0.shape[1]) and Q1.shape == (3 * P1.shape[0], 3 * P1.shape[1])
    v = [rng.normal(size=P1.shape[1]) for _ in range(3)]
    fine = [P0 @ (P1 @ x) for x in v]
    np.testing.assert_allclose(Q0 @ (Q1 @ np.concatenate(v)), fine[0] + w[:, 0] * fine[1] + w[:, 1] * fine[2], atol=1e-12)
    one = augmented_hierarchy(lattice_hierarchy(ijk), w[:, 0])
    column = augmented_hierarchy(lattice_hierarchy(ijk), w[:, :1])
    for _ in range(2):
        assert (next(one) != next(column)).nnz == 0
    with pytest.raises(ValueError, match=r"augment must be .*\(729, k\)"):
        GeometricMultigrid(sp.eye(len(ijk), format="csr"), ijk, augment=np.column_stack([w[:, 0], 0 * w[:, 1]]))


def test_order_two_iterations_at_a_coarse_level():
    """Spacing 0.2, CG with the multigrid forced: poisson-cut 31 iterations (47 with the P1 coarse
    space alone), laplace-beltrami-cut (its order-2 default, the normal-gradient term tau_N h^-1: 13; the
    face stabilization 32, and 67 at 0.1 with phi_h v alone) at most 40."""
    poisson = cutfem.run("poisson-cut", levels=[0.2], order=2, solver="cg-mg").records[0]
    assert poisson["solver"] == "cg-mg" and poisson["solver_iterations"] <= 35, poisson["solver_iterations"]
    lb = cutfem.run("laplace-beltrami-cut", levels=[0.2], order=2, solver="cg-mg").records[0]
    assert lb["solver"] == "cg-mg" and lb["solver_iterations"] <= 40, lb["solver_iterations"]


@pytest.mark.slow
@pytest.mark.parametrize("problem", ["poisson-cut", "laplace-beltrami-cut", "mean-curvature-cut"])
def test_order_two_iterations_flat(problem):
    """Spacings 0.1 and 0.05, each problem's defaults at order 2: at most 40 iterations, the second
    within 3 of the first (measured: poisson-cut 29, 29; laplace-beltrami-cut 13, 13;
    mean-curvature-cut 27, 30)."""
    its = [r["solver_iterations"] for r in cutfem.run(problem, levels=[0.1, 0.05], order=2, solver="cg-mg").records]
    assert max(its) <= 40 and its[1] <= its[0] + 3, its
