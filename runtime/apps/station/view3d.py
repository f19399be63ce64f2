"""The stable 3D view (viser), in SLAM's world frame: map features as clickable markers with
their ids and 3-sigma ellipsoids, features being initialised as their rays, the camera's
trajectory and frustum with the live image on it, the head's posture, the known target, the
operator's labels and virtual objects; and the GUI: what a click in the view does (fixate,
label, box, arrow), the modes, the emergency stop and reset, the wearer's prompt.

The view reads the loop's newest snapshot at its own rate (``rate_hz``) in its own thread; a
click becomes an action submitted to the loop, answered in the GUI.
"""

from __future__ import annotations

import contextlib
import io
import math
import secrets
import threading

import cv2
import numpy as np

from . import actions as A
from .geometry import ellipsoid_mesh, feature_near_ray
from .live import LiveStation, Snapshot

#: The header by which the gate vouches for what it tunnels to viser.
GATE_HEADER = "X-Wvr-Gate"
MARKER_RADIUS_M = 0.008
FRUSTUM_SCALE_M = 0.08
FRUSTUM_IMAGE_WIDTH = 240
TRAJECTORY_MAX = 600
#: Re-send the heavy parts of the scene (ellipsoids, the frustum's image, the trajectory) this often.
HEAVY_EVERY_S = 4.0
#: A marker is moved when its feature has moved more than this, m.
MOVE_M = 0.002
NO_SHADOW = {"cast_shadow": False, "receive_shadow": False}


def _wxyz(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


class View3D:
    """viser's server on loopback (the station's gate tunnels to it) and its scene and GUI."""

    def __init__(self, station: LiveStation, port: int = 0, rate_hz: float = 4.0):
        import viser

        self.station = station
        self.rate_hz = rate_hz
        #: The gate adds this header to what it tunnels; a websocket without it is closed before
        #: any of the scene is sent (a local process knocking on viser's loopback port directly).
        self.gate_secret = secrets.token_urlsafe(18)
        self.refused = 0
        with contextlib.redirect_stdout(io.StringIO()):   # viser prints its own (ungated) address
            self.server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
        self.port = self.server.get_port()
        self._gate_websocket()
        s = self.server.scene
        s.set_up_direction("+z")
        # Flat lighting, no shadows, no environment map: the operator's machine may render in
        # software, and every scene change is a full re-render there.
        s.configure_default_lights(True, cast_shadow=False)
        s.configure_environment_map(None)
        s.add_frame("/world", axes_length=0.15, axes_radius=0.004)
        s.add_grid("/grid", width=4.0, height=4.0, cell_size=0.25, position=(0.0, 0.0, 0.0), shadow_opacity=0.0)
        self._markers: dict[int, object] = {}
        self._labels: dict[int, object] = {}
        self._objects: dict[int, object] = {}
        self._frustum = None
        self._target = None
        self._marker_at: dict[int, np.ndarray] = {}
        self._had_rays = False
        self._heavy_t = -np.inf
        self._framed = False
        self._seq = -1
        self._halt = threading.Event()
        self.updates = 0
        g = self.server.gui
        self.status = g.add_markdown("starting...")
        self.prompt = g.add_markdown("")
        self.tool = g.add_dropdown("click in 3D", ("fixate", "label", "box", "arrow"), initial_value="fixate")
        self.text = g.add_text("label text", initial_value="here")
        self.mode = g.add_button_group("mode", A.OPERATOR_MODES)
        self.stop_button = g.add_button("EMERGENCY STOP", color="red")
        self.reset_button = g.add_button("reset")
        self.answer = g.add_markdown("")
        self.mode.on_click(lambda ev: self._submit(A.SetMode(ev.target.value)))
        self.stop_button.on_click(lambda _: self._submit(A.Stop("operator's 3D view")))
        self.reset_button.on_click(lambda _: self._submit(A.Reset()))
        s.on_click()(self._background_click)

    def _frame_the_map(self, v) -> None:
        """Once SLAM has its target: the grid on the target's plane and the view (initial, and
        every client's) from behind and above the camera, looking at the target."""
        c = v.xyz[v.known].mean(axis=0)
        back = v.T_world_cam[:3, 3] - c
        back[2] = 0.0
        back = back / max(np.linalg.norm(back), 1e-9)
        eye = c + 0.6 * back + np.array([0.0, 0.0, 0.9])      # above the bench, on the wearer's side
        self.server.scene.add_grid("/grid", width=4.0, height=4.0, cell_size=0.25, position=(c[0], c[1], c[2]),
                                   shadow_opacity=0.0)
        k = v.xyz[v.known]
        self.server.scene.add_line_segments("/target", np.stack([k, np.roll(k, -1, axis=0)], axis=1),
                                            colors=(0, 200, 220), thickness=2, thickness_units="screen")
        self.server.initial_camera.position = eye
        self.server.initial_camera.look_at = c
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        for client in self.server.get_clients().values():
            client.camera.up_direction = (0.0, 0.0, 1.0)
            client.camera.position = eye
            client.camera.look_at = c
        self._framed = True

    def _gate_websocket(self) -> None:
        """Close every websocket that did not come through the gate. viser's transport layer
        (``viser.infra``) runs its connect callbacks before it streams the scene's backlog; the
        request's headers are on its connection object (not public API: if it cannot be read,
        the callback raises and viser drops the connection: the check fails closed)."""
        ws = self.server._websock_server
        secret = self.gate_secret.encode()

        async def check(conn) -> None:
            import hmac

            c = getattr(ws, "_live_connections", {}).get(conn.client_id)
            try:
                given = c.request.headers.get(GATE_HEADER)
            except AttributeError:
                self.refused += 1
                raise ConnectionRefusedError("the station cannot check this connection's origin; refused") from None
            if given is None or not hmac.compare_digest(given.encode(), secret):
                self.refused += 1
                await c.close(1008, "open the station's own address with its token")

        ws.on_client_connect(check)

    # ------------------------------------------------------------------ clicks
    def _submit(self, action) -> A.ActionResult:
        res = self.station.request(action, "3d")
        self.answer.content = f"**{action.name}**: " + ("accepted" if res.accepted else f"refused: {res.reason}")
        return res

    def _for_point(self, feature: int | None = None, xyz=None) -> A.ActionResult:
        tool = self.tool.value
        if tool == "fixate":
            return self._submit(A.Fixate(feature=feature, xyz=None if feature is not None else xyz))
        if tool == "label":
            return self._submit(A.AddLabel(self.text.value or "label", feature=feature,
                                           xyz=None if feature is not None else xyz))
        size = np.full(3, 0.05) if tool == "box" else np.array([0.0, 0.0, 0.1])
        return self._submit(A.AddObject(tool, size, feature=feature, xyz=None if feature is not None else xyz))

    def click_feature(self, feature_id: int) -> A.ActionResult:
        """What a click on feature ``feature_id``'s marker does (the tool chosen in the GUI)."""
        return self._for_point(feature=int(feature_id))

    def _background_click(self, ev) -> None:
        snap = self.station.latest()
        if snap is None:
            return
        o, d = np.asarray(ev.ray_origin, float), np.asarray(ev.ray_direction, float)
        d = d / np.linalg.norm(d)
        v = snap.view.xyz - o
        miss = np.linalg.norm(v - np.outer(v @ d, d), axis=1)
        if len(miss) and miss.min() <= 1.5 * MARKER_RADIUS_M:
            return                          # on a marker: its own on_click answers it
        fid = feature_near_ray(snap.view, o, d)
        if fid is None:
            self.answer.content = "no map feature under that click"
            return
        self.click_feature(fid)

    # ------------------------------------------------------------------ updates
    def start(self) -> "View3D":
        self._thread = threading.Thread(target=self._run, name="station-3d", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._halt.set()
        if getattr(self, "_thread", None) is not None:
            self._thread.join(5.0)
        self.server.stop()

    def _run(self) -> None:
        while not self._halt.is_set():
            snap = self.station.wait_newer(self._seq, 0.5)
            if snap is not None:
                try:
                    self.update(snap)
                except Exception as e:  # noqa: BLE001 - a display error never stops the station
                    self.answer.content = f"display error: {e}"
                self._seq = snap.seq
            if self.station.finished.is_set():
                self.status.content = "**the station's loop has ended**"
                return
            self._halt.wait(1.0 / self.rate_hz)

    def update(self, snap: Snapshot) -> None:
        """Bring the scene up to ``snap``. Cheap changes (poses, moved markers, rays) every
        update; heavy ones (the ellipsoid mesh, the frustum's image, the trajectory) at most every
        ``HEAVY_EVERY_S``: each re-sent mesh or image costs the browser a full re-render, and a
        software-rendered page spends its time there instead of on the camera view."""
        import time

        s, v = self.server.scene, snap.view
        now = time.monotonic()
        heavy = now - self._heavy_t >= HEAVY_EVERY_S
        with self.server.atomic():
            # Features: markers (target points cyan) with their ids, clickable.
            ids = set(int(i) for i in v.ids)
            for fid in list(self._markers):
                if fid not in ids:
                    self._markers.pop(fid).remove()
                    self._marker_at.pop(fid, None)
            for fid, p, known in zip(v.ids, v.xyz, v.known):
                fid = int(fid)
                h = self._markers.get(fid)
                if h is None:
                    h = s.add_icosphere(f"/map/f{fid}", radius=MARKER_RADIUS_M, subdivisions=1,
                                        color=(0, 200, 220) if known else (240, 200, 0), position=p,
                                        **NO_SHADOW)
                    s.add_label(f"/map/f{fid}/id", str(fid), position=(0.0, 0.0, 2 * MARKER_RADIUS_M))
                    h.on_click(lambda ev, fid=fid: self.click_feature(fid))
                    self._markers[fid] = h
                    self._marker_at[fid] = p.copy()
                elif np.linalg.norm(p - self._marker_at[fid]) > MOVE_M:
                    h.position = p
                    self._marker_at[fid] = p.copy()
            if heavy and len(v.ids):
                V, F = ellipsoid_mesh(v.xyz, v.cov)
                s.add_mesh_simple("/map/ellipsoids", V, F, color=(120, 160, 255), opacity=0.25, **NO_SHADOW)
            # Features being initialised: their rays over the depth interval.
            if len(v.ray_ids) or self._had_rays:
                far = np.minimum(v.ray_depth[:, 1], 6.0)
                seg = np.stack([v.ray_origin + v.ray_depth[:, :1] * v.ray_direction,
                                v.ray_origin + far[:, None] * v.ray_direction], axis=1)
                s.add_line_segments("/map/rays", seg.reshape(-1, 2, 3), colors=(255, 120, 0), thickness=1.5, thickness_units="screen")
                self._had_rays = len(v.ray_ids) > 0
            # The camera: trajectory, frustum with the live image, the head's posture.
            tr = snap.trajectory[-TRAJECTORY_MAX:]
            if heavy and len(tr) > 1:
                s.add_line_segments("/trajectory", np.stack([tr[:-1], tr[1:]], axis=1), colors=(255, 255, 255),
                                    thickness=1.5, thickness_units="screen")
            if v.localised:
                cam = self.station.camera
                colour = (255, 60, 60) if snap.estop else (60, 220, 60)
                if self._frustum is None or heavy:
                    small = cv2.resize(snap.image, (FRUSTUM_IMAGE_WIDTH, int(FRUSTUM_IMAGE_WIDTH * cam.height / cam.width)),
                                       interpolation=cv2.INTER_AREA)
                    fov = 2 * math.atan(cam.height / (2 * cam.fy))
                    self._frustum = s.add_camera_frustum("/camera", fov=fov, aspect=cam.width / cam.height,
                                                         scale=FRUSTUM_SCALE_M, image=small, format="jpeg",
                                                         jpeg_quality=70, wxyz=_wxyz(v.T_world_cam[:3, :3]),
                                                         position=v.T_world_cam[:3, 3], color=colour, **NO_SHADOW)
                else:
                    self._frustum.wxyz = _wxyz(v.T_world_cam[:3, :3])
                    self._frustum.position = v.T_world_cam[:3, 3]
                    self._frustum.color = colour
                if np.isfinite(snap.T_world_joints).all():
                    j = snap.T_world_joints
                    s.add_line_segments("/head", np.stack([j[:-1], j[1:]], axis=1), colors=(255, 60, 200), thickness=4, thickness_units="screen")
            if np.isfinite(snap.target).all():
                if self._target is None:
                    self._target = s.add_icosphere("/gaze_target", radius=1.6 * MARKER_RADIUS_M, color=(255, 0, 0),
                                                   opacity=0.5, subdivisions=1, position=snap.target, **NO_SHADOW)
                else:
                    self._target.position = snap.target
                    self._target.visible = True
            elif self._target is not None:
                self._target.visible = False
            # The operator's labels and virtual objects.
            for lb in snap.labels:
                if lb.id not in self._labels:
                    self._labels[lb.id] = s.add_label(f"/labels/l{lb.id}", lb.text, position=lb.xyz)
            for ob in snap.objects:
                if ob.id in self._objects:
                    continue
                if ob.kind == "box":
                    self._objects[ob.id] = s.add_box(f"/objects/o{ob.id}", dimensions=tuple(ob.size), position=ob.xyz,
                                                     color=(0, 220, 220), opacity=0.5, **NO_SHADOW)
                else:
                    self._objects[ob.id] = s.add_line_segments(f"/objects/o{ob.id}", ob.edges(), colors=(230, 0, 230),
                                                               thickness=4, thickness_units="screen")
        if heavy:
            self._heavy_t = now
        if not self._framed and v.localised and v.known.any():
            self._frame_the_map(v)
        st = f"t **{snap.t:.2f} s** | mode **{snap.mode}** | {len(v.ids)} features, {len(v.ray_ids)} initialising | " \
             f"loop {snap.loop_hz:.1f} Hz" + (" | **E-STOP LATCHED**" if snap.estop else "")
        self.status.content = st
        self.prompt.content = f"**Wearer:** {snap.prompt}" if snap.prompt else ""
        self.updates += 1
