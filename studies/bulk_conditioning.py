"""Conditioning of fictitious-domain Poisson (symmetric Nitsche + ghost penalty, docs/math.md §8).

The system matrix on V_h^NEG (P1 on the tets that meet Omega_h = {phi_h < 0}) is

    K = A + N_gamma + gamma_g G,
    A = (grad u, grad v)_{Omega_h},
    N_gamma = -(n . grad u, v)_Gamma - (u, n . grad v)_Gamma + (gamma / h_T) (u, v)_Gamma,
    G = sum_{F in G_NEG} h_F ([n_F . grad u], [n_F . grad v])_F,

for Omega the unit ball (radius 1) in a structured Kuhn box of cell spacing s (the box grows with the
ball by 0.1 and is rounded outward to multiples of s, so the grid nodes stay at multiples of s
however the centre moves).  Defaults gamma = 10, gamma_g = 0.1.

What is measured (:func:`spectrum_record`): the extreme eigenvalues of the diagonally scaled matrix
S = |D|^{-1/2} K |D|^{-1/2}, D = diag K (|D|: a small gamma can make a diagonal entry negative, and
the congruence keeps the inertia), and

* ``kappa`` = max |lambda| / min |lambda|, the 2-norm condition number of S (lambda_max / lambda_min
  when S is positive definite);
* ``indefinite``: S (and K) has a negative eigenvalue (:func:`cutfem.solvers.diagnose.condition_number`: the
  signs of the symmetric LDL^T pivots, or the dense spectrum for small matrices).

Indefinite matrices keep their finite condition number in the tables and figures, and are marked
there, never dropped.

1. Over the position of the ball relative to the grid: the centre moved by a uniformly random
   vector in [0, s)^3 (seeded), at a fixed spacing s, for three methods: gamma = 10 with ghost
   penalty (the method), gamma = 10 without ghost penalty (gamma_g = 0: kappa is unbounded over the
   positions, and the matrix may become indefinite on small cuts), and a too small Nitsche penalty
   with ghost penalty (indefinite for some positions).  Reported per method: min, median, max of
   kappa, the ratio max / min, the number of indefinite matrices.
2. Under refinement with ghost penalty: kappa at several spacings, each over a few random positions
   (the same seed), and the exponent p of the least-squares fit max_shifts kappa ~ s^(-p) in the cell
   spacing s (the local size h_T of docs/math.md §7 is proportional to it); the theory gives p = 2.
   Also reported: the exponent between consecutive spacings.  It is far below 2 on coarse grids:
   there the smallest eigenvalue of S belongs to a mode tied to the boundary terms, of a size
   nearly independent of s (kappa about 80-90 for s = 0.4 and 0.2), and only once the smooth
   first Dirichlet mode drops below it, lambda_min(S) ~ pi^2 s^2 / 6 (lumped mass s^3 over the
   diagonal 6 s of the stiffness), near s = 0.15 for the unit ball, does kappa grow like
   (3 / 1.6) s^-2.

Outputs (prefix ``bulk_conditioning``): ``.json`` (everything), ``_shifts.csv`` and ``_h.csv`` (one
row per matrix), ``.png`` / ``.pdf`` (two panels: kappa over the positions; kappa against s).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.forms import assemble
from cutfem.fem.terms import face_jump_penalty, nitsche, stiffness
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.markers import NEG
from cutfem.solvers.diagnose import condition_number
from cutfem.fem.spaces import CutSpace
from cutfem.problems.common import background_for
from cutfem.runs.convergence import new_figure

from .common import PAGE_WIDTH, figure_style, pick, save_csv, save_figure, save_json, study_main

NAME = "bulk_conditioning"
OUTPUTS = [NAME, f"{NAME}_shifts", f"{NAME}_h"]
GAMMA = 10.0
GAMMA_G = 0.1
SMALL_GAMMA = 0.5
RADIUS = 1.0
SEED = 2024

#: the methods compared over the positions: (key, label, Nitsche gamma, ghost-penalty gamma_g)
METHODS = (
    ("ghost", rf"$\gamma = {GAMMA:g}$, $\gamma_g = {GAMMA_G:g}$", GAMMA, GAMMA_G),
    ("no_ghost", rf"$\gamma = {GAMMA:g}$, no ghost penalty", GAMMA, 0.0),
    ("small_gamma", rf"$\gamma = {SMALL_GAMMA:g}$, $\gamma_g = {GAMMA_G:g}$", SMALL_GAMMA, GAMMA_G),
)


def _say(progress, msg):
    if progress:
        progress(msg)


class PoissonParts:
    """The pieces of the fictitious-domain Poisson matrix on one cut, assembled once each.

    ``space`` is V_h^NEG; ``stiffness`` A (n x n CSR), ``ghost`` G (n x n CSR, h_F^1), and
    :meth:`nitsche` N_gamma (cached per gamma); :meth:`matrix` returns A + N_gamma + gamma_g G.
    ``order`` 2: P2 fields on the cut lifted by Theta_h, the ghost penalty of order 2 and the Nitsche
    penalty gamma k^2, as poisson-cut builds them (docs/math.md §17-§18).
    """

    def __init__(self, center, spacing: float, radius: float = RADIUS, order: int = 1):
        center = np.asarray(center, dtype=float)
        if center.shape != (3,) or not np.all(np.isfinite(center)):
            raise ValueError(f"center must be three finite numbers, got {center!r}")
        if not spacing > 0:
            raise ValueError(f"spacing must be positive, got {spacing!r}")
        levelset = Sphere(radius=radius, center=center)
        self.spacing, self.order = float(spacing), int(order)
        self.cut = cut_mesh(background_for(levelset, spacing, anchored=True), levelset, order=order)  # the grid stays, the ball moves
        self.space = CutSpace(self.cut, NEG, order=order)
        self.stiffness = assemble(stiffness(self.cut.dx(NEG)), self.space).tocsr()
        self.ghost = assemble(face_jump_penalty(self.cut.dF(self.cut.ghost_facets(NEG)), h_power=1), self.space).tocsr()
        self._nitsche = {}

    def nitsche(self, gamma: float):
        """N_gamma (n x n CSR) of :func:`cutfem.fem.terms.nitsche` with the penalty gamma k^2 at order k
        (poisson-cut's), assembled once per gamma."""
        if gamma not in self._nitsche:
            self._nitsche[gamma] = assemble(nitsche(self.cut.ds(), gamma * self.order**2), self.space).tocsr()
        return self._nitsche[gamma]

    def matrix(self, gamma: float = GAMMA, gamma_g: float = GAMMA_G):
        """K = A + N_gamma + gamma_g G (CSR)."""
        K = self.stiffness + self.nitsche(gamma)
        return (K + gamma_g * self.ghost if gamma_g else K).tocsr()


def spectrum_record(K) -> dict:
    """The record of one matrix from :func:`cutfem.solvers.diagnose.condition_number`: ``kappa`` (the 2-norm
    condition number of |D|^{-1/2} K |D|^{-1/2}), ``indefinite``, ``singular``, the eigenvalue of
    least magnitude and the largest one (of the scaled matrix), and how many diagonal entries are
    negative (basis functions of negative energy)."""
    kappa = condition_number(K)
    return {
        "dofs": int(K.shape[0]),
        "kappa": float(kappa),
        "indefinite": kappa.cause == "indefinite",
        "singular": kappa.cause in ("singular", "over-stabilized"),
        "lambda_nearest_zero": kappa.smallest,
        "lambda_max": kappa.largest,
        "negative_diagonal": int(np.sum(K.diagonal() < 0)),
    }


def random_centers(count: int, spacing: float, seed: int = SEED) -> np.ndarray:
    """(count, 3) centres uniformly random in [0, spacing)^3 (numpy default_rng(seed))."""
    return np.random.default_rng(seed).uniform(0.0, spacing, size=(count, 3))


def shift_study(spacing: float, n_shifts: int, methods=METHODS, seed: int = SEED, progress=None) -> list[dict]:
    """One row per (position, method): the centre, the method's gamma and gamma_g, and the fields of
    :func:`spectrum_record`, plus the seconds spent in the eigenvalue computation."""
    rows = []
    for i, c in enumerate(random_centers(n_shifts, spacing, seed)):
        if i % 10 == 0:
            _say(progress, f"spacing {spacing:g}: positions {i + 1}-{min(i + 10, n_shifts)} of {n_shifts}")
        parts = PoissonParts(c, spacing)
        for key, _, gamma, gamma_g in methods:
            t0 = time.perf_counter()
            spec = spectrum_record(parts.matrix(gamma, gamma_g))
            rows.append({"shift": i, "center": c.tolist(), "spacing": spacing, "method": key, "gamma": gamma, "gamma_g": gamma_g,
                         **spec, "eigen_seconds": time.perf_counter() - t0})
    return rows


def summarize(rows: list[dict], method: str) -> dict:
    """min / median / max of kappa over the positions of one method, ratio = max / min, and the
    number of indefinite matrices (kappa of indefinite matrices included: the 2-norm condition number)."""
    sel = [r for r in rows if r["method"] == method]
    k = np.array([r["kappa"] for r in sel], dtype=float)
    fin = k[np.isfinite(k)]
    return {
        "count": len(sel),
        "kappa_min": float(fin.min()) if fin.size else None,
        "kappa_median": float(np.median(fin)) if fin.size else None,
        "kappa_max": float(k.max()) if k.size else None,
        "ratio": float(k.max() / k.min()) if k.size else None,
        "indefinite": int(sum(r["indefinite"] for r in sel)),
        "negative_diagonal": int(sum(r["negative_diagonal"] > 0 for r in sel)),
        "singular": int(np.sum(~np.isfinite(k))),
    }


def fitted_exponent(spacings, kappas) -> float | None:
    """p of the least-squares fit log kappa = c - p log s over the finite values (None with fewer than 2)."""
    s, k = np.asarray(spacings, float), np.asarray(kappas, float)
    ok = np.isfinite(k) & (k > 0)
    return float(-np.polyfit(np.log(s[ok]), np.log(k[ok]), 1)[0]) if ok.sum() >= 2 else None


def refinement_study(spacings, n_shifts: int, seed: int = SEED, progress=None) -> list[dict]:
    """kappa with ghost penalty (gamma = 10, gamma_g = 0.1) at each spacing over n_shifts random
    positions in [0, s)^3: one row per spacing with the min / median / max over the positions and
    the largest eigen-solve time."""
    out = []
    for s in spacings:
        _say(progress, f"refinement: spacing {s:g}, {n_shifts} positions")
        t0 = time.perf_counter()
        rows = shift_study(s, n_shifts, methods=METHODS[:1], seed=seed)
        k = np.array([r["kappa"] for r in rows])
        out.append({
            "spacing": s,
            "dofs": int(np.median([r["dofs"] for r in rows])),
            "kappa_min": float(k.min()),
            "kappa_median": float(np.median(k)),
            "kappa_max": float(k.max()),
            "indefinite": int(sum(r["indefinite"] for r in rows)),
            "eigen_seconds_max": float(max(r["eigen_seconds"] for r in rows)),
            "seconds": time.perf_counter() - t0,
        })
    return out


def run(out: Path, size: str = "quick", progress=None) -> dict:
    out = Path(out)
    # full: the positions at spacing 0.1 (about 5800 unknowns each), in the asymptotic range
    shift_spacing = pick(size, 0.4, 0.2, 0.1)
    n_shifts = pick(size, 6, 30, 30)
    spacings = pick(size, [0.4, 0.2], [0.4, 0.2, 0.1], [0.4, 0.2, 0.1, 0.05])
    n_ref = pick(size, 2, 3, 3)

    t0 = time.perf_counter()
    rows = shift_study(shift_spacing, n_shifts, seed=SEED, progress=progress)
    shift_seconds = time.perf_counter() - t0
    by_method = {key: summarize(rows, key) for key, *_ in METHODS}
    ref = refinement_study(spacings, n_ref, seed=SEED, progress=progress)
    exponent = {k: fitted_exponent([r["spacing"] for r in ref], [r[k] for r in ref]) for k in ("kappa_max", "kappa_median")}
    # the exponent between consecutive spacings: coarse grids are pre-asymptotic (see the module docstring)
    exponent["kappa_max_local"] = [fitted_exponent([a["spacing"], b["spacing"]], [a["kappa_max"], b["kappa_max"]])
                                   for a, b in zip(ref, ref[1:])]

    summary = {
        "size": size,
        "domain": f"ball of radius {RADIUS:g}, centre uniform in [0, s)^3, structured Kuhn box",
        "seed": SEED,
        "shifts": {
            "spacing": shift_spacing,
            "count": n_shifts,
            "methods": {key: {"label": label, "gamma": g, "gamma_g": gg, **by_method[key]} for key, label, g, gg in METHODS},
            "seconds": shift_seconds,
            "records": rows,
        },
        "refinement": {
            "gamma": GAMMA,
            "gamma_g": GAMMA_G,
            "positions_per_spacing": n_ref,
            "exponent": exponent,  # kappa ~ s^(-exponent), least squares over the spacings
            "records": ref,
        },
    }
    paths = [save_json(out, NAME, summary), save_csv(out, f"{NAME}_shifts", rows), save_csv(out, f"{NAME}_h", ref)]
    paths += plot(out, rows, ref, exponent, shift_spacing)
    _print_table(summary, paths)
    return {
        "size": size,
        "shift_spacing": shift_spacing,
        "n_shifts": n_shifts,
        **{f"{key}_{k}": v for key in by_method for k, v in by_method[key].items() if k in ("ratio", "kappa_max", "indefinite")},
        "exponent": exponent["kappa_max"],
        "exponent_median": exponent["kappa_median"],
        "exponent_local": exponent["kappa_max_local"],
        "refinement_kappa_max": [r["kappa_max"] for r in ref],
        "spacings": [r["spacing"] for r in ref],
        "paths": [str(p) for p in paths],
    }


def _print_table(summary, paths):
    sh = summary["shifts"]
    print(f"{sh['count']} random positions of the unit ball at spacing {sh['spacing']:g}:")
    print(f"  {'method':<14}{'kappa min':>11}{'median':>11}{'max':>11}{'max/min':>10}{'indefinite':>12}")
    for key, m in sh["methods"].items():
        print(f"  {key:<14}{m['kappa_min']:>11.3g}{m['kappa_median']:>11.3g}{m['kappa_max']:>11.3g}{m['ratio']:>10.3g}"
              f"{m['indefinite']:>7d} of {m['count']}")
    ref = summary["refinement"]
    print(f"with ghost penalty under refinement ({ref['positions_per_spacing']} positions per spacing):")
    print(f"  {'spacing':>8}{'dofs':>8}{'kappa min':>11}{'max':>11}{'eig s':>8}")
    for r in ref["records"]:
        print(f"  {r['spacing']:>8g}{r['dofs']:>8d}{r['kappa_min']:>11.3g}{r['kappa_max']:>11.3g}{r['eigen_seconds_max']:>8.2f}")
    e = ref["exponent"]["kappa_max"]
    singular = [r["spacing"] for r in ref["records"] if not np.isfinite(r["kappa_max"])]
    over = f" (over the finite values; singular at spacing {', '.join(f'{v:g}' for v in singular)})" if singular else ""
    print(f"  fitted: max kappa ~ s^(-p), p = {e:.2f}{over}" if e is not None else f"  fitted exponent: --{over}")
    print("  p between consecutive spacings: " + ", ".join("--" if v is None else f"{v:.2f}" for v in ref["exponent"]["kappa_max_local"]))
    for p in paths:
        print(p)


@figure_style
def plot(out: Path, rows: list[dict], ref: list[dict], exponent: dict, spacing: float) -> list[Path]:
    """The two-panel figure at its printed size (PNG and PDF, :func:`save_figure`): kappa over the
    positions per method (open markers: indefinite), and max / median kappa with ghost penalty
    against the spacing with an s^-2 slope.  ``exponent`` holds the fitted ``kappa_max`` exponent and
    the list ``kappa_max_local``."""
    from matplotlib.ticker import NullFormatter

    fig, (ax1, ax2) = new_figure(PAGE_WIDTH, 3.4, nrows=1, ncols=2, gridspec_kw={"width_ratios": [1.8, 1]})
    styles = {"ghost": ("k", "o", "-"), "no_ghost": ("C3", "s", "--"), "small_gamma": ("C0", "^", ":")}
    for key, label, *_ in METHODS:
        sel = [r for r in rows if r["method"] == key]
        if not sel:
            continue
        color, marker, ls = styles[key]
        x = np.array([r["shift"] + 1 for r in sel])
        k = np.array([r["kappa"] for r in sel])
        ind = np.array([r["indefinite"] for r in sel])
        text = f"{label} (max/min {k.max() / k.min():.3g}" + (f", {ind.sum()} of {len(sel)} indefinite)" if ind.any() else ")")
        # the legend shows the line's marker: filled unless every position is indefinite
        ax1.semilogy(x, k, color=color, ls=ls, lw=0.7, marker=marker, mfc="none" if ind.all() else color,
                     markevery=np.flatnonzero(~ind).tolist(), label=text)
        if ind.any():
            ax1.semilogy(x[ind], k[ind], ls="none", marker=marker, mfc="none", mec=color)
    ax1.set_xlabel("position of the ball (random shift of its centre)")
    ax1.set_ylabel(r"$\kappa(|D|^{-1/2} K |D|^{-1/2})$")
    ax1.set_title(f"spacing {spacing:g}; open markers: indefinite", loc="left")
    ax1.legend(loc="upper left", fontsize=7)
    ax1.set_ylim(top=ax1.get_ylim()[1] * 30)  # room for the legend above the curves
    ax1.grid(True, which="major", alpha=0.3)

    s = np.array([r["spacing"] for r in ref])
    kmax = np.array([r["kappa_max"] for r in ref])
    kmed = np.array([r["kappa_median"] for r in ref])
    local = exponent["kappa_max_local"]
    ax2.loglog(s, kmax, color="k", marker="o", label="max over positions")
    ax2.loglog(s, kmed, color="gray", marker="x", ls="--", label="median over positions")
    if len(s):
        ax2.loglog(s, kmax[-1] * (s / s[-1]) ** -2.0, color="C1", ls=":", label=r"$s^{-2}$")
    if local and local[-1] is not None:
        ax2.annotate(f"finest pair: $s^{{{-local[-1]:.2f}}}$", (0.04, 0.06), xycoords="axes fraction")
    ax2.set_xlabel("cell spacing $s$")
    ax2.set_ylabel(r"$\kappa$ with ghost penalty")
    ax2.set_title(rf"$\gamma = {GAMMA:g}$, $\gamma_g = {GAMMA_G:g}$", loc="left")
    ax2.xaxis.set_minor_formatter(NullFormatter())
    ax2.set_xticks(s)
    ax2.set_xticklabels([f"{v:g}" for v in s])
    ax2.invert_xaxis()
    ax2.legend(loc="center left", fontsize=7)
    ax2.grid(True, which="major", alpha=0.3)
    return save_figure(fig, out, NAME)


main = study_main(run, NAME)

if __name__ == "__main__":
    raise SystemExit(main())
