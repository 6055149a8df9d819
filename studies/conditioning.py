"""Conditioning of the cut mean-curvature system, with and without the face stabilization.

The system matrix of docs/math.md §3 on a cut surface is K = M + tau_F J_F (tau_E = 0, face term without a
power of h as in the paper).  We report the 2-norm condition number of the diagonally scaled matrix
D^{-1/2} K D^{-1/2} (:func:`cutfem.solvers.diagnose.condition_number`), for tau_F = 1/10 (stabilized) and
tau_F = 0 (K = M, the surface mass matrix on the active nodes).

1. Against h: the torus (R, r) = (1, 1/2) on the paper's box [-1.6,1.6]^2 x [-0.6,0.6] cut into
   cubes of side 0.4/k (Kuhn tetrahedra), h = N^(-1/3).
2. Against the position of the surface relative to the grid: a unit sphere whose centre is moved by
   a uniformly random vector in [0, s)^3 (s the grid spacing; seeded), at fixed s.  Also recorded
   per shift: the smallest diagonal entry of M relative to the largest (how small the smallest
   "cut" of a basis function is).

Without stabilization K = M is *always* singular on a cut surface: the discrete level set phi_h is
itself a function of V_h (its nodal values on the active nodes) and vanishes on S_h, so M phi_h = 0.
(The right-hand side A x is orthogonal to phi_h as well, so the unstabilized system is consistent
and its trace on S_h is unique, but the matrix has no finite condition number.)  We therefore
compute the extreme eigenvalues of the scaled matrix ourselves (:func:`scaled_spectrum`: Lanczos
for the largest, shift-invert Lanczos at a small negative shift for the six smallest, dense for
small matrices) and report

* ``kappa``: lambda_max / lambda_min, infinite when lambda_min <= 1e-13 lambda_max (numerically
  singular: 1e-13 is the relative pivot threshold of :class:`cutfem.solvers.solve.DirectSolver`);
* ``kernel_dimension``: the number of such eigenvalues, and for tau_F = 0 the alignment
  |<v_min, phi_h>| (in the scaled coordinates) of the null vector with phi_h;
* ``kappa_effective``: lambda_max over the smallest eigenvalue above the threshold, the condition
  number on the complement of the kernel (what CG sees on a consistent system);
* ``kappa_solve_module``: :func:`cutfem.solvers.diagnose.condition_number` for comparison.  For the stabilized
  matrix it agrees with ``kappa``; for the singular unstabilized matrix it returns a finite number,
  sometimes huge (~1e17, written as infinite: beyond 1e13 it is 1 over round-off) and sometimes
  equal to ``kappa_effective`` (its shift-invert Lanczos at 0 on a singular factorization can miss
  the null vector), so it must not be read as a condition number there.

``lambda_min`` of a singular matrix is written as 0: its computed value is round-off.

Singular values are drawn on a separate "singular" line above the plots and counted, never dropped.

Outputs (prefix ``conditioning``): ``.json``, ``_h.png/.pdf`` (condition number against h with
fitted slopes), ``_shifts.png/.pdf`` (distribution over the shifts and dependence on the smallest
cut), ``_table.tex``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from cutfem.geometry.cut import CUT, cut_mesh
from cutfem.fem.forms import assemble
from cutfem.fem.terms import face_jump_penalty, mass
from cutfem.geometry.shapes import Sphere, Torus
from cutfem.solvers.diagnose import condition_number, scaled
from cutfem.fem.spaces import CutSpace
from cutfem.problems.common import background_for
from cutfem.runs.convergence import significant

from .common import PAGE_WIDTH, figure_style, pick, save_figure, save_json, save_latex_table, study_main

NAME = "conditioning"
OUTPUTS = [NAME, f"{NAME}_h", f"{NAME}_shifts", f"{NAME}_table"]
PAPER_BOX = "-1.6,-1.6,-0.6,1.6,1.6,0.6"
TAU_F = 0.1
SINGULAR = 1e13
SEED = 2024


def _say(progress, msg):
    if progress:
        progress(msg)


def scaled_spectrum(A, n_small: int = 6):
    """Extreme eigenvalues of the diagonally scaled symmetric matrix S = D^{-1/2} A D^{-1/2}.

    Returns (lambda_max, the n_small smallest eigenvalues ascending, their eigenvectors (n, n_small)).
    Dense ``eigh`` up to 300 unknowns; otherwise Lanczos for lambda_max and shift-invert Lanczos
    at sigma = -1e-8 lambda_max (S - sigma I is positive definite even when S is singular, so the
    factorization is safe and the null vectors are found).  Lanczos starts from a seeded random
    vector, so that reruns give the same digits.
    """
    import scipy.sparse.linalg as spla

    S, _ = scaled(A)
    n = S.shape[0]
    if n <= 300:
        ev, vec = np.linalg.eigh(S.toarray())
        return float(ev[-1]), ev[:n_small], vec[:, :n_small]
    v0 = np.random.default_rng(0).standard_normal(n)
    lmax = float(spla.eigsh(S, k=1, which="LA", tol=1e-8, v0=v0, return_eigenvectors=False)[0])
    ev, vec = spla.eigsh(S, k=n_small, sigma=-1e-8 * lmax, which="LM", tol=1e-12, v0=v0)
    order = np.argsort(ev)
    return lmax, ev[order], vec[:, order]


def scaled_condition(A) -> float:
    """lambda_max / lambda_min of the diagonally scaled matrix from :func:`scaled_spectrum`; inf when
    lambda_min <= 1e-13 lambda_max (numerically singular)."""
    lmax, small, _ = scaled_spectrum(A, n_small=1)
    return float("inf") if abs(small[0]) <= SINGULAR**-1 * lmax else float(lmax / small[0])


def _finite_or_inf(kappa: float) -> float:
    """A condition number, infinite beyond :data:`SINGULAR` (numerically singular: beyond it the
    number is 1 over round-off and differs between machines)."""
    return float("inf") if not kappa < SINGULAR else float(kappa)


def _kappa(A, null_candidate=None):
    """Scaled condition numbers of A (see the module docstring)."""
    lmax, small, vec = scaled_spectrum(A)
    zero = np.abs(small) <= SINGULAR**-1 * lmax
    k = int(zero.sum())
    rec = {
        "kappa": float("inf") if k else float(lmax / small[0]),
        "singular": bool(k),
        "kernel_dimension": k,
        "lambda_max": lmax,
        # a zero eigenvalue's computed value and the "condition number" of a singular matrix are
        # round-off (they change with the machine): written as 0 and infinity, like ``kappa``
        "lambda_min": 0.0 if k else float(small[0]),
        "kappa_effective": float(lmax / small[k]) if k < len(small) else None,
        "kappa_solve_module": _finite_or_inf(condition_number(A)),
    }
    if null_candidate is not None and k:
        d = np.sqrt(A.diagonal())
        v = null_candidate * d
        rec["null_vector_alignment_with_phi_h"] = float(abs(vec[:, 0] @ v) / np.linalg.norm(v))
    return rec


def matrices(levelset, spacing, box=None):
    """(space, M, J_F) of the cut of ``levelset`` on a structured background of the given spacing
    (without ``box``: the grid's nodes at multiples of the spacing, so that a surface moved against
    the grid moves against fixed nodes)."""
    cut = cut_mesh(background_for(levelset, spacing, box=box, anchored=True), levelset)
    space = CutSpace(cut)
    M = assemble(mass(cut.ds()), space).tocsr()
    return space, M, assemble(face_jump_penalty(cut.dF(cut.interior_facets(CUT))), space).tocsr()


def _measure(space, M, J):
    st = _kappa(M + TAU_F * J)
    un = _kappa(M, null_candidate=space.cut.values)
    d = M.diagonal()
    rec = {"h": space.h, "dofs": int(space.n_dofs)}
    for tag, r in (("stabilized", st), ("unstabilized", un)):
        rec[f"kappa_{tag}"] = r.pop("kappa")
        rec[f"singular_{tag}"] = r.pop("singular")
        rec.update({f"{k}_{tag}": v for k, v in r.items()})
    rec["min_mass_diagonal_ratio"] = float(d.min() / d.max())
    return rec


def _slope(h, k):
    """Exponent s of a least-squares fit k ~ h^(-s) over the finite values (None with fewer than 2)."""
    h, k = np.asarray(h, float), np.asarray([np.nan if v is None else v for v in k], float)
    ok = np.isfinite(k)
    return float(-np.polyfit(np.log(h[ok]), np.log(k[ok]), 1)[0]) if ok.sum() >= 2 else None


def _stats(rows, key):
    v = np.array([np.nan if r[key] is None else r[key] for r in rows], dtype=float)
    fin = v[np.isfinite(v)]
    return {
        "min": float(fin.min()) if fin.size else None,
        "median": float(np.median(fin)) if fin.size else None,
        "max": float(fin.max()) if fin.size else None,
        "infinite": int(np.sum(~np.isfinite(v))),
    }


def run(out: Path, size: str = "quick", progress=None) -> dict:
    out = Path(out)
    ks = pick(size, [2, 3], [2, 3, 4, 5, 6], [2, 3, 4, 5, 6, 8, 10])
    n_shifts = pick(size, 8, 30, 50)
    shift_spacing = pick(size, 0.25, 0.15, 0.1)

    torus = Torus(R=1.0, r=0.5)
    h_rows = []
    for k in ks:
        s = 0.4 / k
        _say(progress, f"torus spacing {s:.4g}")
        space, M, J = matrices(torus, s, box=PAPER_BOX)
        h_rows.append({"spacing": s, **_measure(space, M, J)})

    rng = np.random.default_rng(SEED)
    shifts = rng.uniform(0.0, shift_spacing, size=(n_shifts, 3))
    shift_rows = []
    for i, c in enumerate(shifts):
        if i % 10 == 0:
            _say(progress, f"sphere shifts {i + 1}-{min(i + 10, n_shifts)} of {n_shifts}")
        space, M, J = matrices(Sphere(radius=1.0, center=c), shift_spacing)
        shift_rows.append({"shift": c.tolist(), **_measure(space, M, J)})

    h = [r["h"] for r in h_rows]
    growth = {
        "kappa_stabilized": _slope(h, [r["kappa_stabilized"] for r in h_rows]),
        "kappa_effective_unstabilized": _slope(h, [r["kappa_effective_unstabilized"] for r in h_rows]),
    }
    sing = lambda rows, tag: int(sum(r[f"singular_{tag}"] for r in rows))  # noqa: E731
    summary = {
        "size": size,
        "tau_f": TAU_F,
        "singular_threshold": SINGULAR,
        "torus": {
            "box": PAPER_BOX,
            "growth_exponent": growth,  # kappa ~ h^(-exponent), least squares over the levels
            "singular_stabilized": sing(h_rows, "stabilized"),
            "singular_unstabilized": sing(h_rows, "unstabilized"),
            "records": h_rows,
        },
        "shifts": {
            "surface": "unit sphere, centre shifted uniformly in [0, s)^3",
            "spacing": shift_spacing,
            "count": n_shifts,
            "seed": SEED,
            "kappa_stabilized": _stats(shift_rows, "kappa_stabilized"),
            "kappa_effective_unstabilized": _stats(shift_rows, "kappa_effective_unstabilized"),
            "kappa_solve_module_unstabilized": _stats(shift_rows, "kappa_solve_module_unstabilized"),
            "min_mass_diagonal_ratio": _stats(shift_rows, "min_mass_diagonal_ratio"),
            "singular_stabilized": sing(shift_rows, "stabilized"),
            "singular_unstabilized": sing(shift_rows, "unstabilized"),
            "records": shift_rows,
        },
    }
    save_json(out, NAME, summary)
    _plot_h(out, significant(h_rows), significant(growth))  # the digits the tables carry
    _plot_shifts(out, significant(shift_rows), shift_spacing)

    def fk(v):
        return r"$\infty$" if v is None or not math.isfinite(v) else f"{v:.2e}"

    rows = [[f"{r['spacing']:.4g}", f"{r['h']:.4f}", str(r["dofs"]), fk(r["kappa_stabilized"]), fk(r["kappa_unstabilized"]),
             str(r["kernel_dimension_unstabilized"]), fk(r["kappa_effective_unstabilized"])] for r in h_rows]
    sh = summary["shifts"]
    rows.append([f"{n_shifts} shifts", f"s={shift_spacing:g}", "", "max " + fk(sh["kappa_stabilized"]["max"]),
                 f"{sh['singular_unstabilized']}/{n_shifts} " + r"$\infty$", "", "max " + fk(sh["kappa_effective_unstabilized"]["max"])])
    save_latex_table(out, f"{NAME}_table", ["spacing", "$h$", "dofs", r"$\kappa$, $\tau_F=0.1$", r"$\kappa$, $\tau_F=0$",
                                            r"$\dim\ker M$", r"$\kappa_{\mathrm{eff}}$, $\tau_F=0$"], rows)
    return {
        "size": size,
        "growth_exponent": growth,
        "torus_kappa_stabilized": [r["kappa_stabilized"] for r in h_rows],
        "torus_kappa_effective_unstabilized": [r["kappa_effective_unstabilized"] for r in h_rows],
        "torus_singular_unstabilized": summary["torus"]["singular_unstabilized"],
        "shifts_kappa_stabilized": sh["kappa_stabilized"],
        "shifts_kappa_effective_unstabilized": sh["kappa_effective_unstabilized"],
        "shifts_singular_unstabilized": sh["singular_unstabilized"],
        "shifts_singular_stabilized": sh["singular_stabilized"],
    }


def _cap(values):
    """The height of the "singular" line: a decade above the largest finite value, drawn as infinity."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return 10.0 ** (math.ceil(math.log10(max(finite))) + 1)


def _infinity_line(ax, cap, text):
    ax.axhline(cap, color="gray", lw=0.8, ls=":")
    ax.set_ylim(top=cap * 3)
    ticks = [t for t in ax.get_yticks() if t < cap * 0.9 and t > 0]
    ax.set_yticks(ticks + [cap])
    ax.set_yticklabels([f"$10^{{{int(round(math.log10(t)))}}}$" for t in ticks] + [r"$\infty$"])
    ax.set_ylim(top=cap * 3)
    ax.annotate(text, (0.02, cap), xycoords=("axes fraction", "data"), xytext=(0, -11), textcoords="offset points", color="gray")


@figure_style
def _plot_h(out, rows, growth):
    from matplotlib.ticker import NullFormatter

    from cutfem.runs.convergence import new_figure

    fig, ax = new_figure(4.2, 3.4)
    h = np.array([r["h"] for r in rows])
    cap = _cap([r[k] for r in rows for k in ("kappa_stabilized", "kappa_effective_unstabilized")])
    ks = np.array([r["kappa_stabilized"] for r in rows])
    ax.loglog(h, ks, color="k", marker="o", label=rf"$\tau_F = {TAU_F}$: $\kappa$ (slope $h^{{-{growth['kappa_stabilized']:.2f}}}$)")
    ke = np.array([np.nan if r["kappa_effective_unstabilized"] is None else r["kappa_effective_unstabilized"] for r in rows])
    ge = growth["kappa_effective_unstabilized"]
    ax.loglog(h, ke, color="C3", marker="x", ls="--",
              label=r"$\tau_F = 0$: $\kappa$ on $(\ker M)^\perp$" + (f" (slope $h^{{-{ge:.2f}}}$)" if ge is not None else ""))
    sing = np.array([r["singular_unstabilized"] for r in rows])
    ax.loglog(h[sing], np.full(sing.sum(), cap), ls="none", marker="v", ms=9, color="C3",
              label=r"$\tau_F = 0$: $\kappa = \infty$ ($\phi_h \in \ker M$)")
    sing_s = np.array([r["singular_stabilized"] for r in rows])
    if sing_s.any():
        ax.loglog(h[sing_s], np.full(sing_s.sum(), cap), ls="none", marker="v", ms=9, color="k", label=rf"$\tau_F = {TAU_F}$: singular")
    _infinity_line(ax, cap, r"singular: $\lambda_{\min} \leq 10^{-13}\lambda_{\max}$")
    ax.set_xlabel(r"$h = N^{-1/3}$ (background nodes)")
    ax.set_ylabel(r"scaled condition number of $K = M + \tau_F J_F$")
    ax.set_title("Cut torus on the paper's box")
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xticks(h)
    ax.set_xticklabels([f"{v:.3f}" for v in h])
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(loc="best")  # where it hides no point: the curves' heights vary with the levels run
    save_figure(fig, out, f"{NAME}_h")


@figure_style
def _plot_shifts(out, rows, spacing):
    from cutfem.runs.convergence import new_figure

    fig, (ax1, ax2) = new_figure(PAGE_WIDTH, 3.2, nrows=1, ncols=2)
    cap = _cap([r[k] for r in rows for k in ("kappa_stabilized", "kappa_effective_unstabilized")])
    ratio = np.array([r["min_mass_diagonal_ratio"] for r in rows])
    x = np.arange(1, len(rows) + 1)
    ks = np.sort([r["kappa_stabilized"] for r in rows])
    ke = np.sort([np.nan if r["kappa_effective_unstabilized"] is None else r["kappa_effective_unstabilized"] for r in rows])
    n_sing = sum(r["singular_unstabilized"] for r in rows)
    ax1.semilogy(x, ks, color="k", marker="o", ms=4, lw=0.8, label=rf"$\tau_F = {TAU_F}$: $\kappa$ (max {np.nanmax(ks):.3g})")
    ax1.semilogy(x, ke, color="C3", marker="x", ms=4, lw=0.8, ls="--",
                 label=r"$\tau_F = 0$: $\kappa$ on $(\ker M)^\perp$" + f" (max {np.nanmax(ke):.3g})")
    ax1.semilogy(x, np.full(len(x), cap), ls="none", marker="v", ms=5, color="C3",
                 label=rf"$\tau_F = 0$: $\kappa = \infty$ ({n_sing} of {len(rows)})")
    ax2.loglog(ratio, [r["kappa_stabilized"] for r in rows], ls="none", marker="o", ms=5, color="k", label=rf"$\tau_F = {TAU_F}$: $\kappa$")
    ax2.loglog(ratio, [np.nan if r["kappa_effective_unstabilized"] is None else r["kappa_effective_unstabilized"] for r in rows],
               ls="none", marker="x", ms=6, color="C3", label=r"$\tau_F = 0$: $\kappa$ on $(\ker M)^\perp$")
    _infinity_line(ax1, cap, r"singular: $\lambda_{\min} \leq 10^{-13}\lambda_{\max}$")
    lo, hi = ax2.get_ylim()
    ax2.set_ylim(top=hi * (hi / lo) ** 0.25)
    ax1.legend(loc="center right")
    ax2.legend(loc="upper center")
    for ax in (ax1, ax2):
        ax.grid(True, which="both", alpha=0.3)
    ax1.set_xlabel("grid position (sorted by condition number)")
    ax1.set_ylabel("scaled condition number")
    ax1.set_title(f"Unit sphere, {len(rows)} grid positions, spacing {spacing:g}")
    ax2.set_xlabel(r"smallest cut: $\min_i M_{ii} / \max_i M_{ii}$")
    ax2.set_ylabel("scaled condition number")
    ax2.set_title("Against the smallest cut")
    save_figure(fig, out, f"{NAME}_shifts")


main = study_main(run, NAME)

if __name__ == "__main__":
    raise SystemExit(main())
