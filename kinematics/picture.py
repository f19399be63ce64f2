"""A picture of a head: its part boxes, joint axes and optic axis, rendered offscreen with pyvista."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .chain import forward_kinematics
from .geometry import LINK_NAMES, HeadGeometry

_COLOURS = {"servo": "#333333", "camera": "#3355cc", "bracket": "#aaaaaa"}
_AXIS_COLOURS = ("#d62728", "#2ca02c", "#1f77b4")


def render_head(head: HeadGeometry, path: str | Path, postures=None, size=(900, 700)) -> Path:
    """Write a PNG of the head at ``postures`` ((k, 3) joint angles, radians; the first drawn solid,
    the rest translucent). Joint axes are drawn for the first posture, coloured elevation red, pan
    green, cyclotorsion blue; the optic axis as a yellow arrow. Each link is drawn joined as built:
    a grey strip from its joint's shaft (the link frame's origin, on the driving motor's horn) to
    every servo or camera it carries. Units in the picture: millimetres.
    Returns the path written (``.png`` is added to a path without it)."""
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")  # headless
    import pyvista as pv

    postures = np.zeros((1, 3)) if postures is None else np.atleast_2d(np.asarray(postures, float))
    plotter = pv.Plotter(off_screen=True, window_size=list(size))
    plotter.set_background("white")
    for k, q in enumerate(postures):
        pose = forward_kinematics(head, q)
        T = {"mount": np.eye(4)}
        for i, name in enumerate(LINK_NAMES[1:]):
            T[name] = pose.T_mount_link[i]
        opacity = 1.0 if k == 0 else 0.25
        for p in head.parts:
            box = pv.Box(bounds=np.ravel(np.column_stack([np.asarray(p.center_m) - np.asarray(p.size_m) / 2,
                                                          np.asarray(p.center_m) + np.asarray(p.size_m) / 2])))
            box.points = box.points * 1000.0
            M = T[p.link].copy()
            M[:3, 3] *= 1000.0
            plotter.add_mesh(box.transform(M, inplace=False), color=_COLOURS[p.kind], opacity=opacity,
                             show_edges=k == 0)
        for name in LINK_NAMES[1:]:
            shaft = T[name][:3, 3] * 1000.0
            for p in head.parts_on(name):
                if p.kind != "bracket":
                    end = (T[name][:3, :3] @ np.asarray(p.center_m) + T[name][:3, 3]) * 1000.0
                    if np.linalg.norm(end - shaft) > 1e-6:
                        plotter.add_mesh(pv.Tube(pointa=shaft, pointb=end, radius=2.0, n_sides=12),
                                         color=_COLOURS["bracket"], opacity=opacity)
            plotter.add_mesh(pv.Sphere(radius=3.0, center=shaft), color="#555555", opacity=opacity)
        c = pose.p_mount_cam * 1000.0
        plotter.add_mesh(pv.Arrow(start=c, direction=pose.optic_axis, scale=60.0), color="#e6b800", opacity=opacity)
        if k == 0:
            for i in range(3):
                o = pose.origins_mount[i] * 1000.0
                a = pose.axes_mount[i]
                plotter.add_mesh(pv.Line(o - 35 * a, o + 35 * a), color=_AXIS_COLOURS[i], line_width=4)
    plotter.add_text("axes: elevation red, pan green, cyclotorsion blue; optic axis yellow; "
                     "brackets grey (shaft to the part carried)", font_size=8, color="black")
    plotter.add_axes()
    plotter.camera_position = [(160.0, -220.0, 160.0), (20.0, 0.0, 40.0), (0.0, 0.0, 1.0)]
    plotter.reset_camera()   # the same view direction, fitted to every part of any layout
    plotter.camera.zoom(1.4)
    path = Path(path)
    if path.suffix.lower() != ".png":
        path = path.with_name(path.name + ".png")   # what the screenshot writes; report the true name
    plotter.screenshot(str(path))
    plotter.close()
    return path
