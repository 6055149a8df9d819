"""Issue 45, items 2d, 2e and the messages of part 4 that concern forms and parameters: inputs that
gave a wrong number without a word, or a message that named neither the cause nor the fix.

Expected numbers come from the mathematics, never from the code under test: the integral of a
constant c over a measure is c times its size (the sum of the P1 basis integrals is the size,
since the basis functions sum to one); the penalty ranges are those stated in the docstrings.
"""

import re

import numpy as np
import pytest

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.forms import assemble, bilinear_form, linear_form
from cutfem.fem.pointwise import ZERO
from cutfem.fem.terms import mass
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.markers import NEG
from cutfem.geometry.box import structured_box
from cutfem.fem.spaces import CutSpace


@pytest.fixture(scope="module")
def cut():
    return cut_mesh(structured_box([-1.2] * 3, [1.2] * 3, spacing=0.4), Sphere(0.8))


# --- 2e: w.at(f) must never return the values of another function --------------------------------

def test_w_at_gives_each_inline_function_its_own_values(cut):
    """Functions made inline in a loop are freed after each call, so CPython gives the next one the
    same id: a cache keyed by id(f) returned the first function's values for all of them (3 * size
    instead of (1 + 2 + 3) * size)."""
    dx = cut.dx(NEG)
    V = CutSpace(cut, NEG)

    @linear_form
    def constants(v, w):
        total = 0.0
        for c in (1.0, 2.0, 3.0):
            total = total + w.at(lambda x, c=c: np.full(x.shape[:-1], c))
        return total * v

    b = assemble(constants * dx, V)
    assert b.sum() == pytest.approx(6.0 * dx.size, rel=1e-12)


def test_w_at_still_evaluates_a_named_function_once_per_block(cut):
    """The cache keyed by the function itself keeps its purpose: one evaluation per block of cells
    for a function defined once, however many basis pairs the integrand is evaluated for."""
    dx = cut.dx(NEG)
    V = CutSpace(cut, NEG)
    calls = []

    def f(x):
        calls.append(x.shape[0])
        return np.ones(x.shape[:-1])

    @bilinear_form
    def weighted(u, v, w):
        return w.at(f) * u * v

    K = assemble(weighted * dx, V)
    M = assemble(mass(dx), V)
    assert abs(K - M).max() <= 1e-12 * abs(M).max()
    assert len(calls) == len(list(dx.blocks(2)))


# --- part 4: a sum of ZERO terms is ZERO ----------------------------------------------------------

def test_a_sum_of_zero_terms_is_zero_and_couples_nothing(cut):
    """sum() starts from the number 0, and 0 + ZERO was 0: the pair of fields (0, 1) then looked
    coupled and its integrand returned the integer 0, refused for its shape ().  Now the sum is
    ZERO and the matrix is the block-diagonal mass matrix of the two fields."""
    from cutfem.fem.terms import mass
    from cutfem.geometry.markers import POS
    from cutfem.fem.spaces import ProductSpace

    assert sum([ZERO, ZERO]) is ZERO
    assert 0 - ZERO is ZERO and ZERO - 0 is ZERO and 0.0 + ZERO is ZERO
    W = ProductSpace(CutSpace(cut, NEG), CutSpace(cut, POS))
    ds = cut.ds()

    @bilinear_form(symmetric=True)
    def diagonal(u, v, w):
        return sum(u[k] * v[k] for k in range(2))

    K = assemble(diagonal * ds, W)
    M = assemble(mass(ds, field=0) + mass(ds, field=1), W)
    assert abs(K - M).max() <= 1e-12 * abs(M).max()


def test_an_integrand_returning_one_number_is_told_why(cut):
    V = CutSpace(cut, NEG)

    @bilinear_form
    def nothing(u, v, w):
        return 0

    with pytest.raises(ValueError, match=r"returned the single number 0, not values at the quadrature points.*ZERO"):
        assemble(nothing * cut.dx(NEG), V)


# --- 2d: parameters that cost accuracy or mean nothing: the same answer on every path -------------

import json  # noqa: E402

import cutfem  # noqa: E402
from cutfem.runs.cli import main  # noqa: E402
from cutfem.runs.registry import ProblemError  # noqa: E402


def _cli(capsys, *argv):
    """(exit status, standard error) of ``cutfem run ...`` in this process."""
    status = main(["run", *argv, "--quiet"])
    return status, capsys.readouterr().err


def test_a_large_ghost_penalty_warns_on_every_path_and_is_noted(capsys, tmp_path):
    """gamma_g = 1e6 locks u_h to linear functions (L2 error 0.266 against 0.0264 at the default,
    spacing 0.25): a RuntimeWarning naming --gamma-g and the range, and a note in the record and
    its JSON, from cutfem.run and from the command line alike."""
    with pytest.warns(RuntimeWarning, match=r"--gamma-g 1e\+06 is above 1: .*use --gamma-g in \[0.01, 1\]"):
        res = cutfem.run("poisson-cut", levels=[0.25], gamma_g=1e6)
    assert res.records[0]["warnings"][0].startswith("--gamma-g 1e+06 is above 1")
    out = tmp_path / "run.json"
    status, err = _cli(capsys, "poisson-cut", "--levels", "0.25", "--gamma-g", "1e6", "--json", str(out))
    assert status == 0 and err.splitlines()[0].startswith("warning: --gamma-g 1e+06 is above 1: ")  # one line, no source
    assert "RuntimeWarning" not in err
    assert "--gamma-g 1e+06 is above 1" in json.loads(out.read_text())["records"][0]["warnings"][0]


def test_a_default_run_carries_no_warning():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        res = cutfem.run("poisson-cut", levels=[0.25])
    assert "warnings" not in res.records[0]


@pytest.mark.parametrize("value", [1e7, -1.0, float("nan")])
def test_a_meaningless_ghost_penalty_is_refused_on_every_path(capsys, value):
    from cutfem.problems.poisson import poisson_cut

    words = r"--gamma-g:? .*(above 1e\+06.*numerically singular|must be a finite number >= 0|is not a finite number)"
    with pytest.raises(ProblemError, match=words):
        cutfem.run("poisson-cut", levels=[0.25], gamma_g=value)
    status, err = _cli(capsys, "poisson-cut", "--levels", "0.25", "--gamma-g", str(value))
    assert status == 2 and "--gamma-g" in err and "Traceback" not in err
    with pytest.raises(ProblemError, match=r"--gamma-g:? .*(above 1e\+06|>= 0)"):  # the problem's own function
        poisson_cut(0.25, "sphere", "structured", None, 10.0, value, "auto", 1.0, 0.5, 1.0, "1,0.8,0.6")


def test_a_tiny_face_stabilization_is_refused_the_same_way_from_python_and_the_command_line(capsys):
    """tau_F = 1e-10: O(1) errors on the direct path while CG called the system singular; now both
    paths refuse it before solving, naming --tau-f and the range at this spacing."""
    words = r"--tau-f 1e-10: tau_F = 1e-10 is below 1e-06: .*give tau_F in \[0.001, "
    for solver in ("direct", "cg-mg"):
        with pytest.raises(ProblemError, match=words):
            cutfem.run("mean-curvature-cut", levels=[0.2], surface="sphere", tau_f=1e-10, solver=solver)
    status, err = _cli(capsys, "mean-curvature-cut", "--surface", "sphere", "--levels", "0.2", "--tau-f", "1e-10")
    assert status == 2 and re.search(words, err) and err.count("\n") == 1


def test_a_small_face_stabilization_warns_with_the_range():
    with pytest.warns(RuntimeWarning, match=r"--tau-f 0.0001: tau_F = 0.0001 is below 0.001.*give tau_F in \[0.001, "):
        res = cutfem.run("laplace-beltrami-cut", levels=[0.2], tau_f=1e-4)
    assert "below 0.001" in res.records[0]["warnings"][0]


@pytest.mark.parametrize("argv, words", [
    # the constants "were a null vector" and phi_h "was" one: now the flag and the range that fits
    (["--tau-f", "1e300"], r"--tau-f 1e\+300: tau_F = 1e\+300 is .* above 1e\+06 times: .*give tau_F in \[0.001, 4e\+04\]"),
    (["--face-h-power", "50"], r"--tau-f 0.1 with --face-h-power 50: .*below 1e-06: .*give --face-h-power in \[-8.01, 2.86\]"),
])
def test_extreme_stabilization_flags_are_named_with_their_range(capsys, argv, words):
    status, err = _cli(capsys, "mean-curvature-cut", "--surface", "sphere", "--levels", "0.2", *argv)
    assert status == 2 and re.search(words, err), err
    assert "constant functions are a null vector" not in err and "phi_h (zero on S_h) is a null vector" not in err


def test_the_length_scale_is_checked_where_every_path_builds_the_form():
    """A sphere of radius 100 with L = 1: refused by the command line and cutfem.run, but a script
    building the system with mean_curvature_system got a 34 % error without a word."""
    from cutfem.geometry.markers import CUT
    from cutfem.problems.mean_curvature import mean_curvature_system

    big = cut_mesh(structured_box([-120.0] * 3, [120.0] * 3, spacing=20.0), Sphere(100.0))
    V = CutSpace(big)
    faces = big.dF(big.interior_facets(CUT))
    with pytest.raises(ProblemError, match=r"size sqrt\(area / 4 pi\) = 99.5 is 99.5 times the length scale L = 1.*"
                                           r"--length-scale 100 "):
        mean_curvature_system(V, big.ds(), tau_f=0.1, faces=faces)
    K, B = mean_curvature_system(V, big.ds(), tau_f=0.1, faces=faces, length_scale=100.0)
    assert K.shape == (V.n_dofs, V.n_dofs)
    with pytest.raises(ProblemError, match=r"--length-scale 100 "):  # a level set object through cutfem.run
        cutfem.run("mean-curvature-cut", levels=[20.0], surface=Sphere(100.0))


# --- part 4: zero rows with tau_F > 0: the surface lies on grid planes -----------------------------

CUBE = "maximum(maximum(abs(x), abs(y)), abs(z)) - 0.5"


def _cube_system():
    """The mean curvature system of a cube whose faces lie on the grid planes x, y, z = +-0.5."""
    from cutfem.geometry.levelset import FunctionLevelSet
    from cutfem.geometry.markers import CUT
    from cutfem.problems.mean_curvature import mean_curvature_system

    cube = cut_mesh(structured_box([-1.0] * 3, [1.0] * 3, spacing=0.1), FunctionLevelSet.from_expression(CUBE))
    V = CutSpace(cube)
    K, B = mean_curvature_system(V, cube.ds(), tau_f=0.1, faces=cube.dF(cube.interior_facets(CUT)))
    return cube, V, K, B


def test_zero_rows_of_a_surface_on_grid_planes_name_the_cause_and_the_fix():
    """147 nodes off S_h in no term although tau_F = 0.1.  The message said to add a stabilization;
    it now says why none reaches them and what helps."""
    from cutfem.solvers.diagnose import SolverError
    from cutfem.solvers.solve import solve

    cube, V, K, B = _cube_system()
    words = (r"147 unknowns appear in no term .*nodes off S_h .*S_h runs along faces of the background mesh.*"
             r"face stabilization \(any tau_F\) does not reach them.*shift the background box")
    for method in ("direct", "cg-mg"):
        with pytest.raises(SolverError, match=words):
            solve(K, B, method=method, space=V)


def test_the_problem_fixes_the_unknowns_no_term_sees(capsys):
    """cutfem run and cutfem.run refused the cube on grid planes (68 of ~149 such solves); the
    unknowns that no term sees are now fixed at 0 and counted in the record.  Their values change
    nothing on S_h: the other unknowns solve the system without them (checked against the reduced
    system, solved directly)."""
    from cutfem.problems.common import pin_unseen_nodes
    from cutfem.solvers.solve import solve

    res = cutfem.run("mean-curvature-cut", levels=[0.1], surface=CUBE, box="-1,-1,-1,1,1,1", solver="direct")
    assert res.records[0]["unseen_nodes"] == 294
    status, _ = _cli(capsys, "mean-curvature-cut", "--surface", CUBE, "--box", "-1,-1,-1,1,1,1", "--levels", "0.1")
    assert status == 0
    cube, V, K, B = _cube_system()
    Kp, Bp, count = pin_unseen_nodes(K, B, V)
    H, _ = solve(Kp, Bp, method="direct", space=V)
    seen = K.diagonal() > 1e-20  # 147 exact zeros outside the cube, 147 at 1.8e-32 inside
    assert count == 294 and np.all(H[~seen] == 0)
    reduced = K[seen][:, seen].toarray()
    H_seen = np.linalg.solve(reduced, B[seen])
    np.testing.assert_allclose(H[seen], H_seen, rtol=0, atol=1e-9 * np.abs(H_seen).max())


@pytest.mark.parametrize("problem, level, params, words", [
    ("poisson-cut", 0.25, {"gamma": 1e4}, r"--gamma 10000 is above 1000: .*use --gamma in \[10, 100\]"),
    ("laplace-beltrami-cut", 0.2, {"stabilization": "normal", "tau_n": 1e3},
     r"--tau-n 1000: tau_N = 1000 is above 100: .*give tau_N in \[0.01, 1e\+02\]"),
    ("mean-curvature-meshed", 16, {"tau_e": 10.0}, r"--tau-e 10 is above 1: .*give --tau-e in \[0.01, 1\]"),
])
def test_other_penalties_that_cost_accuracy_warn_and_are_noted(problem, level, params, words):
    with pytest.warns(RuntimeWarning, match=words):
        res = cutfem.run(problem, levels=[level], **params)
    assert re.search(words, res.records[0]["warnings"][0])


def test_a_normal_stabilization_that_vanishes_names_both_flags(capsys):
    status, err = _cli(capsys, "laplace-beltrami-cut", "--levels", "0.2", "--stabilization", "normal",
                       "--normal-h-power", "20")
    assert status == 2
    assert re.search(r"--tau-n 1 with --normal-h-power 20: the weight tau_N \(s / L\)\^\(a - 1\) = .* is below 1e-08: "
                     r".*phi_h .* give tau_N in \[.*\] at this power", err), err


def test_w_at_keeps_one_inline_function_per_code(cut):
    """The cache holds each function it was given; an inline lambda, made again for every basis
    pair, replaces the one of the same code before it instead of piling up (correct values, one
    array held)."""
    from cutfem.fem.pointwise import QuadData

    x = np.random.default_rng(0).normal(size=(5, 4, 3))
    w = QuadData(x, None, None, np.arange(5), {})
    for c in range(10):
        assert np.all(w.at(lambda y, c=c: np.full(y.shape[:-1], float(c))) == c)
    assert len(w._values) == 1

    def f(y):
        return y[..., 0]

    def g(y):
        return y[..., 1]

    assert np.array_equal(w.at(f), x[..., 0]) and np.array_equal(w.at(g), x[..., 1]) and len(w._values) == 3
