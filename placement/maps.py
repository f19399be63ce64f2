"""Body maps: each score painted on the body, front and back, darker where placing a camera is
better (as in the paper's Fig. 3); rendered offscreen with pyvista."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .body import Body, Pose
from .scores import ScoreTable

#: Score -> (title, True if higher is better). Motion maps are drawn darker where motion is less.
MAP_SCORES = {
    "fov": ("field of view (fraction of the sphere)", True),
    "handling_view": ("view of the handling space (fraction)", True),
    "motion_mm": ("motion, mm (darker = steadier)", False),
    "combined": ("combined score", True),
}


def render_map(body: Body, values: np.ndarray, path: str | Path, title: str, higher_is_better: bool = True,
               pose: Pose | None = None, size=(900, 800)) -> Path:
    """Write a PNG with front and back views of the body, faces coloured by ``values`` (F,)."""
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    v = body.vertices if pose is None else body.posed_vertices(pose)
    faces = np.hstack([np.full((body.face_count, 1), 3), body.faces]).ravel()
    mesh = pv.PolyData(v, faces)
    mesh.cell_data["score"] = np.asarray(values, float)
    cmap = "Greys" if higher_is_better else "Greys_r"
    # Stretch the grey scale over the bulk of the values so differences between places show.
    clim = np.percentile(values, [2, 98])
    if clim[1] <= clim[0]:
        clim = [float(np.min(values)), float(np.max(values)) + 1e-12]
    centre = v.mean(axis=0)
    dist = 3.6 * (v[:, 2].max() - v[:, 2].min()) / 1.75
    plotter = pv.Plotter(off_screen=True, window_size=list(size), shape=(1, 2), border=False)
    for k, (label, direction) in enumerate((("front", -1.0), ("back", 1.0))):
        plotter.subplot(0, k)
        plotter.set_background("white")
        plotter.add_mesh(mesh.copy(), scalars="score", cmap=cmap, clim=clim, show_edges=False, lighting=True,
                         scalar_bar_args={"title": title, "color": "black", "vertical": False} if k == 0 else None,
                         show_scalar_bar=k == 0)
        plotter.add_text(label, font_size=10, color="black")
        # The body faces -Y: the front view looks from -Y towards +Y.
        plotter.camera_position = [(centre[0], centre[1] + direction * dist, centre[2]), tuple(centre), (0, 0, 1)]
    path = Path(path)
    plotter.screenshot(str(path))
    plotter.close()
    return path


def render_all_maps(body: Body, table: ScoreTable, out: str | Path) -> dict[str, str]:
    """One PNG per score in :data:`MAP_SCORES`; returns score -> file name."""
    out = Path(out)
    files = {}
    for name, (title, better_high) in MAP_SCORES.items():
        p = render_map(body, table[name], out / f"map_{name}.png", title, better_high)
        files[name] = p.name
    return files
