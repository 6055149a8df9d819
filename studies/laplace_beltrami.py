"""Laplace-Beltrami convergence (docs/math.md §4): -Lap_S u + u = f on the sphere and the torus.

Manufactured solutions of :mod:`cutfem.problems.laplace_beltrami` (sphere: u = x y + z; torus:
u = cos(3t) sin(p)).  Four discretizations per surface, all through ``cutfem.run``:

* meshed (``laplace-beltrami-meshed``): icosahedral sphere / structured n x n/2 torus grid,
  no stabilization, h = N^(-1/2);
* cut with the face stabilization tau_F J_F (tau_F = 1/10, no power of h);
* cut with the normal-gradient stabilization tau_N h (n_h . grad u, n_h . grad v)_{T_h}
  (tau_N = 1, power 1); both cut variants on a structured Kuhn background of the surface's box
  grown by 0.1 (for the torus: the paper's box), h = N^(-1/3).

Errors: L2(S_h) and the H1(S_h) seminorm against u^e = u o p; rates by least squares over the
levels (expected 2 and 1 for P1).

Outputs (prefix ``laplace_beltrami``): ``.json``, ``.csv``, ``.png/.pdf`` (2 x 2 panels: sphere /
torus x meshed / cut) and ``_table.tex``.
"""

from __future__ import annotations

from pathlib import Path


import cutfem
from cutfem.fem.norms import fitted_rate
from cutfem.runs.convergence import significant

from .common import PAGE_WIDTH, figure_style, fmt_rate, pick, save_csv, save_figure, save_json, save_latex_table, study_main

NAME = "laplace_beltrami"
OUTPUTS = [NAME, f"{NAME}_table"]


def _say(progress, msg):
    if progress:
        progress(msg)


def _cases(size):
    sphere_n = pick(size, [10, 20, 40], [10, 20, 40, 80], [10, 20, 40, 80, 160, 320])
    torus_n = pick(size, [16, 32, 64], [16, 32, 64, 128], [16, 32, 64, 128, 256])
    spacings = pick(size, [0.2, 0.1], [0.2, 0.1, 0.05], [0.2, 0.1, 0.05, 0.025])
    cases = []
    for surface, ns in (("sphere", sphere_n), ("torus", torus_n)):
        cases.append({"surface": surface, "method": "meshed", "problem": "laplace-beltrami-meshed", "levels": ns, "params": {}})
        cases.append({"surface": surface, "method": "cut, face", "problem": "laplace-beltrami-cut", "levels": spacings,
                      "params": {"stabilization": "face", "tau_f": 0.1, "face_h_power": 0.0}})
        cases.append({"surface": surface, "method": "cut, normal", "problem": "laplace-beltrami-cut", "levels": spacings,
                      "params": {"stabilization": "normal", "tau_n": 1.0, "normal_h_power": 1.0}})
    return cases


def run(out: Path, size: str = "quick", progress=None) -> dict:
    out = Path(out)
    results = []
    rows = []
    for case in _cases(size):
        _say(progress, f"{case['surface']} {case['method']} levels {case['levels']}")
        res = cutfem.run(case["problem"], levels=case["levels"], surface=case["surface"], **case["params"])
        h = [r["h"] for r in res.records]
        l2 = [r["l2_error"] for r in res.records]
        h1 = [r["h1_error"] for r in res.records]
        entry = {
            "surface": case["surface"],
            "method": case["method"],
            "problem": case["problem"],
            "parameters": res.parameters,
            "levels": case["levels"],
            "h": h,
            "dofs": [r["dofs"] for r in res.records],
            "l2_error": l2,
            "h1_error": h1,
            "l2_rate": fitted_rate(h, l2),
            "h1_rate": fitted_rate(h, h1),
            "l2_rates_between_levels": res.rates["l2_error"],
            "h1_rates_between_levels": res.rates["h1_error"],
            "seconds": [r["wall_time"] for r in res.records],
        }
        entry["parameters"] = {k: v for k, v in entry["parameters"].items() if isinstance(v, (int, float, str)) or v is None}
        results.append(entry)
        for i, r in enumerate(res.records):
            rows.append({"surface": case["surface"], "method": case["method"], "level": case["levels"][i], "h": r["h"], "dofs": r["dofs"],
                         "l2_error": r["l2_error"], "h1_error": r["h1_error"], "area": r.get("area"), "seconds": r["wall_time"]})

    summary = {"size": size, "cases": results}
    save_json(out, NAME, summary)
    save_csv(out, NAME, rows)
    _plot(out, significant(results))  # the digits the tables carry
    header = ["surface", "method", "levels", "$h$ (finest)", r"$L^2$ error", "rate", r"$H^1$ error", "rate"]
    table = [[c["surface"], c["method"], str(len(c["h"])), f"{c['h'][-1]:.4f}", f"{c['l2_error'][-1]:.3e}", fmt_rate(c["l2_rate"]),
              f"{c['h1_error'][-1]:.3e}", fmt_rate(c["h1_rate"])] for c in results]
    save_latex_table(out, f"{NAME}_table", header, table, caption="Laplace-Beltrami: errors at the finest level and rates fitted over the levels; "
                     "h = N^{-1/2}, N the surface nodes (meshed), h = N^{-1/3}, N the background nodes (cut).")
    return {
        "size": size,
        "rates": {f"{c['surface']}, {c['method']}": {"l2": c["l2_rate"], "h1": c["h1_rate"]} for c in results},
        "finest_l2_error": {f"{c['surface']}, {c['method']}": c["l2_error"][-1] for c in results},
    }


@figure_style
def _plot(out, results):
    from cutfem.runs.convergence import log_ticks, loglog_with_rates, new_figure, rate_triangle

    fig, axes = new_figure(PAGE_WIDTH, 5.4, nrows=2, ncols=2)
    style = {"meshed": dict(color="C0"), "cut, face": dict(color="C1"), "cut, normal": dict(color="C2", ls="--")}
    for i, surface in enumerate(("sphere", "torus")):
        for j, kind in enumerate(("meshed", "cut")):
            ax = axes[i, j]
            for c in results:
                if c["surface"] != surface or not c["method"].startswith(kind):
                    continue
                tag = "" if kind == "meshed" else c["method"].split(", ")[1] + ": "
                loglog_with_rates(ax, c["h"], c["l2_error"], f"{tag}$L^2$", marker="o", **style[c["method"]])
                loglog_with_rates(ax, c["h"], c["h1_error"], f"{tag}$H^1$", marker="s", mfc="none", **style[c["method"]])
            first = next(c for c in results if c["surface"] == surface and c["method"].startswith(kind))
            rate_triangle(ax, first["h"], first["h1_error"], 1, below=False)
            rate_triangle(ax, first["h"], first["l2_error"], 2)
            ax.set_xlabel(r"$h = N^{-1/2}$ (surface nodes)" if kind == "meshed" else r"$h = N^{-1/3}$ (background nodes)")
            ax.set_ylabel("error")
            ax.set_title(f"{surface}, {kind}")
            ax.grid(True, which="major", alpha=0.3)
            log_ticks(ax)
            ax.legend(loc="best")
    save_figure(fig, out, NAME)


main = study_main(run, NAME)

if __name__ == "__main__":
    raise SystemExit(main())
