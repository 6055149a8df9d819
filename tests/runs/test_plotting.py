"""Tests for cutfem.runs.plotting: PNG pictures rendered off screen (no display needed).

Each picture is read back with matplotlib and must have the requested size and real content: not
a single colour, with a share of non-background (non-white) pixels that a drawn object gives.
"""

import sys
from types import SimpleNamespace

import matplotlib.image as mpimg
import numpy as np
import pytest

from cutfem.geometry.cut import cut_mesh
from cutfem.geometry.shapes import Sphere
from cutfem.geometry.box import structured_box
from cutfem.runs.plotting import offscreen_backend, plot_cut, plot_surface_field, plot_surface_mesh

SIZE = (320, 240)  # width, height in pixels


@pytest.fixture(scope="module")
def small_cut():
    return cut_mesh(structured_box([-2.0] * 3, [2.0] * 3, spacing=0.5), Sphere(1.2, center=(0.05, -0.1, 0.02)))


def check_picture(path):
    assert path.exists() and path.suffix == ".png"
    image = mpimg.imread(path)
    assert image.shape[:2] == (SIZE[1], SIZE[0])
    rgb = image[..., :3]
    assert np.ptp(rgb) > 0.3  # not one colour
    background = np.all(rgb > 0.98, axis=-1)  # white background
    assert 0.02 < 1 - background.mean() < 0.95
    assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 20  # shading / colour map
    return rgb


def test_offscreen_backend_is_available():
    assert isinstance(offscreen_backend(), str)


def test_plot_cut_writes_png(small_cut, tmp_path):
    path = plot_cut(small_cut, tmp_path / "pictures" / "cut.png", clip="y", title="S_h", window_size=SIZE)
    rgb = check_picture(path)
    # the surface colour (gold: high red and green, low blue) is on the picture
    gold = (rgb[..., 0] > 0.6) & (rgb[..., 1] > 0.5) & (rgb[..., 2] < 0.35)
    assert gold.mean() > 0.01


def test_plot_surface_field_vector_and_scalar(small_cut, tmp_path):
    cut = small_cut
    # a vector field per vertex, shown by its magnitude |x| (between about 1 and 1.4 here)
    path = plot_surface_field(cut.vertices, cut.triangles, cut.vertices, tmp_path / "field.png", title="|x|", window_size=SIZE)
    check_picture(path)
    # a scalar field per triangle (the z component of the normal), a fixed colour range
    values = cut.normals[cut.triangle_tets, 2]
    path = plot_surface_field(
        cut.vertices, cut.triangles, values, tmp_path / "nz.png", clim=(-1, 1), cmap="coolwarm", show_edges=True,
        window_size=SIZE,
    )
    check_picture(path)


def test_plot_surface_mesh(tmp_path):
    # the boundary of the unit tetrahedron, as any object with .points and .triangles
    mesh = SimpleNamespace(
        points=np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]),
        triangles=np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]),
    )
    path = plot_surface_mesh(mesh, tmp_path / "tet.png", title="mesh", window_size=SIZE)
    rgb = check_picture(path)
    assert np.mean(np.all(rgb < 0.2, axis=-1)) > 0.001  # black edges are drawn


def test_bad_input(small_cut, tmp_path):
    cut = small_cut
    V, T = len(cut.vertices), len(cut.triangles)
    with pytest.raises(ValueError, match=f"{V} vertices and {T} triangles"):
        plot_surface_field(cut.vertices, cut.triangles, np.ones(V + 1), tmp_path / "a.png")
    with pytest.raises(ValueError, match="only for vector fields"):
        plot_surface_field(cut.vertices, cut.triangles, np.ones(V), tmp_path / "a.png", component=0)
    with pytest.raises(ValueError, match="component must be"):
        plot_surface_field(cut.vertices, cut.triangles, np.ones((V, 3)), tmp_path / "a.png", component=3)
    with pytest.raises(ValueError, match="NaN"):
        plot_surface_field(cut.vertices, cut.triangles, np.full(T, np.nan), tmp_path / "a.png")
    tet_points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    tet_triangles = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # 4 vertices, 4 triangles
    with pytest.raises(ValueError, match="location='point' or location='cell'"):
        plot_surface_field(tet_points, tet_triangles, np.ones(4), tmp_path / "a.png")
    with pytest.raises(ValueError, match="location="):
        plot_surface_field(tet_points, tet_triangles, np.ones(4), tmp_path / "a.png", location="edge")
    with pytest.raises(ValueError, match="clim"):
        plot_surface_field(cut.vertices, cut.triangles, np.ones(V), tmp_path / "a.png", clim=(1, 0))
    with pytest.raises(ValueError, match="indices"):
        plot_surface_field(np.eye(3), [[0, 1, 3]], [1.0, 2.0, 3.0], tmp_path / "a.png")
    with pytest.raises(ValueError, match="clip must be"):
        plot_cut(cut, tmp_path / "a.png", clip="w")
    with pytest.raises(ValueError, match="removes all of S_h"):
        plot_cut(cut, tmp_path / "a.png", clip=((1, 0, 0), (-5, 0, 0)))
    with pytest.raises(ValueError, match="active must be"):
        plot_cut(cut, tmp_path / "a.png", active="solid")
    with pytest.raises(ValueError, match="ending in .png"):
        plot_cut(cut, tmp_path / "a.jpg")
    with pytest.raises(ValueError, match="needs a CutMesh"):
        plot_cut(object(), tmp_path / "a.png")
    with pytest.raises(ValueError, match="triangles"):
        plot_surface_mesh(object(), tmp_path / "a.png")
    assert not any(tmp_path.iterdir())  # nothing was written


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="display detection through DISPLAY is Linux only")
def test_interactive_without_display_asks_for_a_path(small_cut, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(RuntimeError, match="path="):
        plot_cut(small_cut)


def test_convergence_plot_draws_the_records(tmp_path, monkeypatch):
    """The figure of --plot: one curve per error key at the records' h, the least-squares rate in
    each label (none for a key with one point: no 'rate nan' in a figure), one rate triangle per
    slope of the two finest levels with legs of that slope on the log-log axes."""
    from cutfem.runs import convergence
    from cutfem.runs.runner import RunResult

    h = np.array([0.4, 0.2, 0.1])
    records = [{"h": x, "l2_error": 3 * x**2, "h1_error": 0.5 * x} for x in h]
    records[0]["once_error"] = 0.25  # a key of the first level only
    result = RunResult("toy", {"c": 0.5, "box": None}, list(h), records)
    drawn = []
    monkeypatch.setattr(convergence, "save_reproducible", lambda fig, path, dpi=200: drawn.append(fig) or path)
    convergence.convergence_plot(result, tmp_path / "c.png")
    ax = drawn[0].axes[0]
    curves = {line.get_label(): line for line in ax.get_lines()}
    assert set(curves) == {"l2 error (rate 2.00)", "h1 error (rate 1.00)", "once error"}
    np.testing.assert_allclose(curves["l2 error (rate 2.00)"].get_xdata(), h)
    np.testing.assert_allclose(curves["l2 error (rate 2.00)"].get_ydata(), 3 * h**2)
    np.testing.assert_allclose(curves["once error"].get_xdata(), [0.4])
    assert ax.get_xlabel() == "$h$" and ax.get_xscale() == ax.get_yscale() == "log"
    assert ax.get_title(loc="left") == "toy: c=0.5"  # a parameter left to its default rule (None) is not named
    slopes = sorted(np.log(p.get_xy()[1, 1] / p.get_xy()[0, 1]) / np.log(p.get_xy()[1, 0] / p.get_xy()[0, 0]) for p in ax.patches)
    np.testing.assert_allclose(slopes, [1.0, 2.0], rtol=1e-12)
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["l2 error (rate 2.00)", "h1 error (rate 1.00)", "once error"]


def test_every_problem_defines_its_h_and_the_figure_names_it(tmp_path, monkeypatch):
    """Each built-in problem defines h as N^(-1/3) of the background nodes (cut) or N^(-1/2) of the
    surface nodes (meshed), its records' h is that number, and the convergence figure's x label
    states it; a problem without its own definition gets h alone (see the toy above)."""
    from cutfem.runs import convergence
    from cutfem.runs.registry import _ORIGIN, H_AXIS_LABELS, H_BACKGROUND, H_SURFACE, _is_builtin, available_problems
    from cutfem.runs.runner import run

    drawn = []
    monkeypatch.setattr(convergence, "save_reproducible", lambda fig, path, dpi=200: drawn.append(fig) or path)
    builtin = {name: p for name, p in available_problems().items() if _is_builtin(_ORIGIN.get(name) or "")}
    assert len(builtin) >= 8
    for name, problem in builtin.items():
        result = run(name, levels=problem.default_levels[:1])
        rec = result.records[0]
        if result.definitions["h"] == H_SURFACE:
            assert rec["h"] == pytest.approx(rec["dofs"] ** -0.5, rel=1e-12), name  # P1 on the surface: a dof a node
        else:
            assert result.definitions["h"] == H_BACKGROUND, name
            assert rec["h"] == pytest.approx(rec["background_nodes"] ** (-1 / 3), rel=1e-12), name
        convergence.convergence_plot(result, tmp_path / f"{name}.png")
        assert drawn[-1].axes[0].get_xlabel() == H_AXIS_LABELS[result.definitions["h"]]
    assert {H_SURFACE, H_BACKGROUND} <= {p.definitions["h"] for p in builtin.values()}


def test_convergence_plot_leaves_out_keys_without_a_finite_error(tmp_path, monkeypatch, capsys):
    """A key NaN (or zero) at every level is no curve and no legend entry; when no key is left,
    --plot writes nothing and says why (an empty figure would pass for a result)."""
    from cutfem.runs import convergence
    from cutfem.runs.cli import main
    from cutfem.runs.registry import register
    from cutfem.runs.runner import RunResult

    records = [{"h": x, "l2_error": x**2, "nan_error": float("nan"), "zero_error": 0.0} for x in (0.5, 0.25)]
    assert convergence.plotted_keys(RunResult("toy", {}, [0.5, 0.25], records)) == ["l2_error"]
    drawn = []
    monkeypatch.setattr(convergence, "save_reproducible", lambda fig, path, dpi=200: drawn.append(fig) or path)
    convergence.convergence_plot(RunResult("toy", {}, [0.5, 0.25], records), tmp_path / "c.png")
    assert [line.get_label() for line in drawn[0].axes[0].get_lines()] == ["l2 error (rate 2.00)"]
    monkeypatch.undo()

    @register("test-nan-errors", levels=[0.5, 0.25], level_name="step")
    def nan_errors(step):
        return {"h": step, "l2_error": float("nan")}

    plot = tmp_path / "nan.png"
    assert main(["run", "test-nan-errors", "--plot", str(plot), "--quiet"]) == 0
    assert "--plot: nothing written" in capsys.readouterr().err and not plot.exists()


def test_a_curves_rate_is_the_one_fit_over_its_positive_errors():
    """loglog_with_rates fits with cutfem.fem.norms.fitted_rate over the points it draws (e > 0 and
    finite): e = h^2 with a zero and a NaN among them has rate 2; one point left has none."""
    from cutfem.runs.convergence import loglog_with_rates, new_figure

    fig, ax = new_figure(3, 2)
    h = np.array([0.4, 0.2, 0.1, 0.05, 0.025])
    e = h ** 2
    e[1], e[3] = 0.0, np.nan
    assert loglog_with_rates(ax, h, e, "e") == pytest.approx(2.0, abs=1e-12)
    assert ax.get_legend_handles_labels()[1] == ["e (rate 2.00)"]
    assert np.isnan(loglog_with_rates(ax, h[:2], [1e-3, 0.0], "one point"))
