"""Pictures of cuts, surface meshes and fields on surfaces, with pyvista, on screen or off screen.

Every function builds one ``pyvista.Plotter`` and either writes a PNG (``path`` given: rendered off
screen, nothing opens) or shows an interactive window (``path=None``: needs a display).  They
return the path written (a :class:`pathlib.Path`) or ``None`` after an interactive window.

* :func:`plot_cut` -- S_h (opaque) inside its active mesh T_h (tet edges), optionally clipped by a
  plane so that the inside of a closed surface can be seen.
* :func:`plot_surface_field` -- a scalar or vector field on a triangulated surface, per vertex
  (P1, interpolated colours) or per triangle (flat colours); a vector field is shown by its
  magnitude |v| = sqrt(v_x^2 + v_y^2 + v_z^2) or by one component; colour bar and title.
* :func:`plot_surface_mesh` -- a triangle mesh with its edges (anything with ``points`` and
  ``triangles``, or a :class:`~cutfem.geometry.cut.CutMesh`, whose triangles index ``vertices``).

Off screen without a display
----------------------------
VTK wheels (9.4 and later) pick their OpenGL window at run time.  On Linux with neither ``DISPLAY``
nor ``WAYLAND_DISPLAY`` set, the first off-screen picture checks once, in a child process, which
headless window renders (EGL first, then OSMesa) and sets ``VTK_DEFAULT_OPENGL_WINDOW`` to it for
this process (a broken backend can crash the process, hence the child).  If neither works a
``RuntimeError`` says what to install.  A ``VTK_DEFAULT_OPENGL_WINDOW`` set by the user is
respected and not checked.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

__all__ = ["plot_cut", "plot_surface_field", "plot_surface_mesh", "offscreen_backend"]

_HEADLESS_WINDOWS = ("vtkEGLRenderWindow", "vtkOSOpenGLRenderWindow")
_PROBE = (
    "import vtkmodules.vtkRenderingOpenGL2\n"
    "from vtkmodules.vtkRenderingCore import vtkRenderWindow, vtkRenderer\n"
    "w = vtkRenderWindow(); w.SetOffScreenRendering(1); w.AddRenderer(vtkRenderer()); w.SetSize(8, 8)\n"
    "w.Render(); print(w.GetClassName())\n"
)
_backend_checked: str | None = None


def _has_display() -> bool:
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def offscreen_backend() -> str:
    """Make off-screen rendering work in this process and name the OpenGL window used.

    Returns ``"default"`` when a display is available or the user set ``VTK_DEFAULT_OPENGL_WINDOW``
    (its value is then returned), otherwise the headless window that rendered in a child process
    (``"vtkEGLRenderWindow"`` or ``"vtkOSOpenGLRenderWindow"``), which is then set as
    ``VTK_DEFAULT_OPENGL_WINDOW`` for this process.  The check runs once per process.

    Raises RuntimeError when no headless window can render.
    """
    global _backend_checked
    if _backend_checked is not None:
        return _backend_checked
    if os.environ.get("VTK_DEFAULT_OPENGL_WINDOW"):
        _backend_checked = os.environ["VTK_DEFAULT_OPENGL_WINDOW"]
        return _backend_checked
    if _has_display():
        _backend_checked = "default"
        return _backend_checked
    errors = []
    for window in _HEADLESS_WINDOWS:
        env = dict(os.environ, VTK_DEFAULT_OPENGL_WINDOW=window)
        try:
            run = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=120)
        except (OSError, subprocess.TimeoutExpired) as exc:
            errors.append(f"{window}: {exc}")
            continue
        if run.returncode == 0 and window in run.stdout:
            os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = window
            _backend_checked = window
            return window
        errors.append(f"{window}: exit code {run.returncode} {run.stderr.strip()[-200:]}")
    raise RuntimeError(
        "pyvista/VTK cannot render off screen on this machine (no display, and neither EGL nor OSMesa "
        "works: " + "; ".join(errors) + "). Install the EGL or OSMesa libraries (e.g. apt-get install "
        "libegl1 or libosmesa6), run under a virtual display (xvfb-run), or save figures with matplotlib."
    )


# ---------------------------------------------------------------------------------------------
# plotter set-up and output
# ---------------------------------------------------------------------------------------------


def _plotter(path, window_size, title):
    if path is None:
        if not _has_display():
            raise RuntimeError("no display to show an interactive window: pass path='picture.png' to save a PNG instead")
    elif Path(path).suffix.lower() != ".png":
        raise ValueError(f"pictures are written as PNG: give a path ending in .png, got {Path(path).name!r}")
    else:
        offscreen_backend()
    import pyvista as pv

    size = tuple(int(s) for s in np.broadcast_to(np.asarray(window_size), (2,)))
    if min(size) < 16:
        raise ValueError(f"window_size must be two pixel counts of at least 16, got {window_size!r}")
    plotter = pv.Plotter(off_screen=path is not None, window_size=size)
    plotter.set_background("white")
    if title:
        plotter.add_text(str(title), position="upper_edge", font_size=12, color="black")
    return plotter


def _finish(plotter, path, camera_position):
    if camera_position is not None:
        plotter.camera_position = camera_position
    else:
        plotter.view_isometric()
    if path is None:
        plotter.show()
        return None
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    plotter.screenshot(str(path))
    plotter.close()
    return path


def _polydata(points, triangles):
    """A ``pyvista.PolyData`` of triangles, after checking shapes, indices and finiteness."""
    import pyvista as pv

    points = np.asarray(points, dtype=float)
    triangles = np.asarray(triangles)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3 or not np.issubdtype(triangles.dtype, np.integer):
        raise ValueError(f"triangles must be an integer array of shape (M, 3), got {triangles.dtype} {triangles.shape}")
    if len(triangles) == 0:
        raise ValueError("there are no triangles to draw")
    if triangles.min() < 0 or triangles.max() >= len(points):
        raise ValueError(f"triangle vertex indices must lie in [0, {len(points)}), got [{triangles.min()}, {triangles.max()}]")
    if not np.all(np.isfinite(points)):
        raise ValueError("points contain NaN or infinite coordinates; fix the mesh before plotting")
    faces = np.hstack([np.full((len(triangles), 1), 3, dtype=np.int64), triangles.astype(np.int64)]).ravel()
    return pv.PolyData(points, faces)


def _clip_plane(clip, centre):
    """(unit normal (3,), origin (3,)) of a clip plane, or None.

    ``clip``: None; an axis name ``"x"``, ``"y"``, ``"z"`` or ``"-x"``... (plane through
    ``centre``); or a pair ``(normal, origin)``.  The half space ``(x - origin) . normal > 0`` is
    removed.
    """
    if clip is None:
        return None
    axes = {"x": 0, "y": 1, "z": 2}
    if isinstance(clip, str):
        name = clip.strip().lower()
        sign = -1.0 if name.startswith("-") else 1.0
        name = name.lstrip("+-")
        if name not in axes:
            raise ValueError(f"clip must be 'x', 'y', 'z' (optionally with a sign) or (normal, origin), got {clip!r}")
        normal = np.zeros(3)
        normal[axes[name]] = sign
        return normal, np.asarray(centre, float)
    try:
        normal, origin = clip
        normal = np.asarray(normal, float).reshape(3)
        origin = np.asarray(origin, float).reshape(3)
    except (TypeError, ValueError):
        raise ValueError(f"clip must be 'x', 'y', 'z' (optionally with a sign) or (normal, origin), got {clip!r}") from None
    length = np.linalg.norm(normal)
    if not np.isfinite(length) or length == 0 or not np.all(np.isfinite(origin)):
        raise ValueError(f"the clip plane needs a nonzero finite normal and a finite origin, got {clip!r}")
    return normal / length, origin


def _keep(centroids, plane):
    """Mask of the elements whose centroid is not in the removed half space (crinkle clip)."""
    if plane is None:
        return np.ones(len(centroids), bool)
    normal, origin = plane
    return (centroids - origin) @ normal <= 0


# ---------------------------------------------------------------------------------------------
# the pictures
# ---------------------------------------------------------------------------------------------


def plot_cut(
    cut,
    path=None,
    *,
    clip=None,
    active: str | None = "wireframe",
    surface_color="gold",
    active_color="steelblue",
    show_surface_edges: bool = True,
    title: str | None = None,
    window_size=(1024, 768),
    camera_position=None,
):
    """S_h of a :class:`~cutfem.geometry.cut.CutMesh` with the active mesh T_h around it.

    Parameters
    ----------
    cut : CutMesh (uses ``vertices``, ``triangles``, ``triangle_tets``, ``points``, ``tets``).
    path : PNG file to write off screen, or None for an interactive window.
    clip : None, an axis ``"x" | "y" | "z" | "-x" | ...`` (plane through the centre of S_h's
        bounding box) or ``(normal, origin)``.  Triangles of S_h and active tets whose centroid lies
        in ``(x - origin) . normal > 0`` are left out (whole elements, no cutting).
    active : ``"wireframe"`` (edges of the active tets), ``"surface"`` (semi-transparent tets with
        edges) or None (S_h only).
    surface_color, active_color : colours of S_h and of the active mesh.
    show_surface_edges : draw the triangle edges of S_h (quadrilateral pieces show their diagonal).
    title : text at the top of the picture.
    window_size : (width, height) in pixels of the picture.
    camera_position : anything pyvista accepts (``"xy"``, ``"iso"``, a camera tuple); default
        isometric.

    Returns
    -------
    The ``Path`` written, or None for an interactive window.
    """
    if active not in ("wireframe", "surface", None):
        raise ValueError(f"active must be 'wireframe', 'surface' or None, got {active!r}")
    for name in ("vertices", "triangles", "points", "tets"):
        if not hasattr(cut, name):
            raise ValueError(f"plot_cut needs a CutMesh (with .{name}); got {type(cut).__name__}")
    import pyvista as pv

    vertices = np.asarray(cut.vertices, float)
    triangles = np.asarray(cut.triangles)
    plane = _clip_plane(clip, 0.5 * (vertices.min(axis=0) + vertices.max(axis=0)))
    keep_tri = _keep(vertices[triangles].mean(axis=1), plane)
    if not np.any(keep_tri):
        raise ValueError("the clip plane removes all of S_h: move the plane or flip its normal")
    plotter = _plotter(path, window_size, title)
    surface = _polydata(vertices, triangles[keep_tri])
    plotter.add_mesh(
        surface,
        color=surface_color,
        show_edges=show_surface_edges,
        edge_color="black",
        line_width=0.5,
        smooth_shading=False,
    )
    if active is not None:
        points = np.asarray(cut.points, float)
        tets = np.asarray(cut.tets)
        keep_tet = _keep(points[tets].mean(axis=1), plane)
        if np.any(keep_tet):
            grid = pv.UnstructuredGrid({pv.CellType.TETRA: tets[keep_tet]}, points)
            if active == "wireframe":
                plotter.add_mesh(grid, style="wireframe", color=active_color, line_width=0.5, opacity=0.35)
            else:
                plotter.add_mesh(grid, color=active_color, opacity=0.15, show_edges=True, edge_color=active_color)
    return _finish(plotter, path, camera_position)


def plot_surface_field(
    points,
    triangles,
    values,
    path=None,
    *,
    location: str | None = None,
    component=None,
    clim=None,
    title: str | None = None,
    cmap: str = "viridis",
    label: str | None = None,
    show_edges: bool = False,
    window_size=(1024, 768),
    camera_position=None,
):
    """A scalar or vector field on a triangulated surface, with a colour bar.

    Parameters
    ----------
    points : (N, 3) vertex coordinates; triangles : (M, 3) vertex indices.
    values : (N,) or (N, 3) per vertex (colours interpolated, a P1 field), or (M,) or (M, 3) per
        triangle (flat colours).  Must be finite.
    location : ``"point"`` or ``"cell"`` when N == M makes the length ambiguous; otherwise inferred.
    component : for vector fields: None or ``"magnitude"`` shows |v| = sqrt(v . v); 0, 1, 2 (or
        ``"x"``, ``"y"``, ``"z"``) shows that component.  Must be None for scalar fields.
    clim : (min, max) of the colour scale; default the range of the values shown.
    title : text at the top; label : colour-bar title (default ``"value"``, ``"magnitude"`` or
        ``"x component"``...).
    cmap : matplotlib colour map name.  show_edges : draw triangle edges.
    path, window_size, camera_position : as in :func:`plot_cut`.

    Returns
    -------
    The ``Path`` written, or None for an interactive window.
    """
    mesh = _polydata(points, triangles)
    values = np.asarray(values, dtype=float)
    n, m = mesh.n_points, mesh.n_cells
    if values.ndim not in (1, 2) or (values.ndim == 2 and values.shape[1] != 3):
        raise ValueError(f"values must have shape (n,) or (n, 3), got {values.shape}")
    if location is None:
        if len(values) == n == m:
            raise ValueError(
                f"{n} vertices and {m} triangles: say whether the values are per vertex or per triangle "
                "with location='point' or location='cell'"
            )
        location = "point" if len(values) == n else "cell" if len(values) == m else None
    if location not in ("point", "cell"):
        raise ValueError(
            f"values have length {len(values)}, but the surface has {n} vertices and {m} triangles "
            "(or pass location='point' or 'cell')"
        )
    expected = n if location == "point" else m
    if len(values) != expected:
        raise ValueError(f"location={location!r} needs {expected} values, got {len(values)}")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"values contain {int(np.sum(~np.isfinite(values)))} NaN or infinite entries; fix the field")
    if values.ndim == 2:
        names = {"x": 0, "y": 1, "z": 2}
        if component is None or component == "magnitude":
            shown, default_label = np.linalg.norm(values, axis=1), "magnitude"
        elif (isinstance(component, str) and component in names) or (
            isinstance(component, (int, np.integer)) and not isinstance(component, bool) and 0 <= component <= 2
        ):
            k = names[component] if isinstance(component, str) else int(component)
            shown, default_label = values[:, k], f"{'xyz'[k]} component"
        else:
            raise ValueError(f"component must be None, 'magnitude', 0, 1, 2, 'x', 'y' or 'z', got {component!r}")
    else:
        if component is not None:
            raise ValueError("component is only for vector fields (values of shape (n, 3))")
        shown, default_label = values, "value"
    label = label or default_label
    if clim is not None:
        clim = [float(c) for c in clim]
        if len(clim) != 2 or not clim[0] < clim[1]:
            raise ValueError(f"clim must be (min, max) with min < max, got {clim!r}")
    elif shown.min() == shown.max():
        clim = [shown.min() - 0.5, shown.max() + 0.5]  # a constant field still gets a colour bar
    if location == "point":
        mesh.point_data[label] = shown
    else:
        mesh.cell_data[label] = shown
    plotter = _plotter(path, window_size, title)
    plotter.add_mesh(
        mesh,
        scalars=label,
        preference=location,
        cmap=cmap,
        clim=clim,
        show_edges=show_edges,
        edge_color="gray",
        interpolate_before_map=True,
        scalar_bar_args={
            "title": label,
            "color": "black",
            "vertical": True,
            "position_x": 0.84,
            "position_y": 0.08,
            "width": 0.08,
            "height": 0.75,
            "fmt": "%.3g",
        },
    )
    return _finish(plotter, path, camera_position)


def plot_surface_mesh(
    mesh,
    path=None,
    *,
    color="lightgray",
    edge_color="black",
    line_width: float = 0.7,
    title: str | None = None,
    window_size=(1024, 768),
    camera_position=None,
):
    """A triangle surface mesh with its edges shown.

    ``mesh`` has ``triangles`` (M, 3) and the coordinates they index: ``vertices`` if it has them
    (a CutMesh, whose ``points`` are the active background nodes), otherwise ``points`` (a
    SurfaceMesh, a pyvista-like object).  Other parameters as in :func:`plot_cut`.

    Returns
    -------
    The ``Path`` written, or None for an interactive window.
    """
    if not hasattr(mesh, "triangles"):
        raise ValueError(f"plot_surface_mesh needs an object with .triangles and .points (or .vertices); got {type(mesh).__name__}")
    coordinates = mesh.vertices if hasattr(mesh, "vertices") else getattr(mesh, "points", None)
    if coordinates is None:
        raise ValueError(f"{type(mesh).__name__} has .triangles but no .points or .vertices")
    poly = _polydata(coordinates, mesh.triangles)
    plotter = _plotter(path, window_size, title)
    plotter.add_mesh(poly, color=color, show_edges=True, edge_color=edge_color, line_width=line_width)
    return _finish(plotter, path, camera_position)
