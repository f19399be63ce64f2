"""The station's explore mode (issue 49): the candidates drawn on the camera view where SLAM's pose
and the lens model put them, coloured by their scores, the chosen one ringed; the mode refused
before SLAM has started; and on the twin, explore chosen from the API moves the head, with the
candidates and scores in the state."""

import http.client
import json
import math
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kinematics import reference_head
from kinematics.camera import default_camera, project, unproject
from runtime.apps.closed_loop import ClosedLoop, Task
from runtime.apps.explore import ExploreChoice
from runtime.apps.station.geometry import EXPLORE_OBJECTIVE, ExploreView
from runtime.apps.station.overlay import EXPLORE_RADIUS_PX, EXPLORE_RING_PX, draw_explore, score_colours
from runtime.robot import ImuSamples, Observation, RobotInfo

CAM = default_camera()


def _pose():
    # A camera 0.3 m off the origin, turned 10 deg about its y and 5 deg about its x.
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("yx", [10.0, 5.0], degrees=True).as_matrix()
    T[:3, 3] = [0.3, -0.1, 0.05]
    return T


def _choice(points, scores, best):
    n = len(points)
    scores = np.asarray(scores, float)
    return ExploreChoice(directions_world=np.tile([0.0, 0.0, 1.0], (n, 1)), points_world=np.asarray(points, float),
                         reachable=np.isfinite(scores), q=np.zeros((n, 3)),
                         pose_info=np.where(np.isfinite(scores), 0.5 * np.nan_to_num(scores, neginf=0.0), 0.0),
                         empty=np.zeros(n), n_visible=np.arange(n), score=scores, best=best)


def _pixel(T, X):
    """The pixel of world point X seen from T, through the lens model (independently of the overlay)."""
    return project(CAM, ((np.asarray(X, float) - T[:3, 3]) @ T[:3, :3])[None])[0]


def test_explore_view_keeps_the_candidates_and_finds_the_chosen_one_at_the_loops_target():
    pts = [[0.0, 0.0, 1.0], [0.5, 0.0, 1.0], [0.0, 0.5, 1.0], [-0.5, 0.0, 1.0]]
    ch = _choice(pts, [1.0, -np.inf, 3.0, 2.0], best=2)
    # The loop took the candidate at [-0.5, 0, 1] (the controller refused the top score).
    ev = ExploreView.of(ch, np.array(pts[3]))
    assert ev.points_world.tolist() == [pts[0], pts[2], pts[3]]         # the unreachable one left out
    assert ev.score.tolist() == [1.0, 3.0, 2.0] and ev.chosen == 2
    assert np.allclose(ev.novelty, ev.score - ev.pose_info) and ev.visible.tolist() == [0, 2, 3]
    assert np.allclose(ev.normalised(), [0.0, 1.0, 0.5])
    assert ExploreView.of(ch, np.full(3, np.nan)).chosen == -1
    assert len(ExploreView.of(None, np.zeros(3)).score) == 0


def test_the_chosen_candidate_is_drawn_at_its_projection_in_its_scores_colour_and_ringed():
    T = _pose()
    # Points in front of the camera, 1.2 m along rays through chosen pixels.
    uv_want = np.array([[200.0, 150.0], [420.0, 300.0], [330.0, 380.0]])
    rays = unproject(CAM, uv_want)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    pts = T[:3, 3] + 1.2 * rays @ T[:3, :3].T
    pts = np.vstack([pts, T[:3, 3] - T[:3, 2]])                          # one behind the camera: not drawn
    ev = ExploreView.of(_choice(pts, [0.7, 2.5, 1.6, 0.1], best=1), pts[0])   # the lowest shown is the chosen
    assert ev.chosen == 0
    img = np.full((CAM.height, CAM.width, 3), 90, np.uint8)
    assert draw_explore(img, CAM, T, ev) == 3
    s = ev.normalised()
    for k in range(3):
        u, v = np.round(_pixel(T, pts[k])).astype(int)
        assert np.abs(img[v, u].astype(int) - score_colours(s[k:k + 1])[0]).max() <= 2, k
    r0, r1 = EXPLORE_RADIUS_PX
    # The chosen one's ring, white, beyond its disc; the others have none.
    for k, ringed in ((0, True), (1, False)):
        u, v = np.round(_pixel(T, pts[k])).astype(int)
        r = int(round(r0 + (r1 - r0) * s[k])) + EXPLORE_RING_PX
        ring = img[v - 1:v + 2, u - r - 1:u - r + 2].reshape(-1, 3)
        assert (ring.min(axis=1) > 200).any() == ringed, k
    # The legend states the objective: light pixels along the bottom line, none in a blank image's.
    assert (img[CAM.height - 20:CAM.height - 8, 8:300] > 200).all(axis=2).sum() > 50


def test_every_operator_mode_has_its_button_on_the_page():
    from runtime.apps.station.actions import OPERATOR_MODES
    from runtime.apps.station.pages import operator_page

    page = operator_page("token", "wearer")
    assert "explore" in OPERATOR_MODES
    for mode in OPERATOR_MODES:
        assert f'data-mode="{mode}"' in page, mode


class _StillCamera:
    """A robot that sees one textured image and holds its joints: enough to start a loop."""

    def __init__(self):
        head = reference_head()
        self.info = RobotInfo(head, CAM, 20.0, head.max_speed, name="still")
        rng = np.random.default_rng(0)
        self.image = (rng.random((CAM.height, CAM.width, 3)) * 255).astype(np.uint8)

    def obs(self, t):
        return Observation(t, self.image, ImuSamples(), np.zeros(3), q_source="commanded")


def test_explore_is_refused_before_slam_has_started_and_the_mode_stays():
    robot = _StillCamera()
    loop = ClosedLoop(robot.info, Task("fixate", start="head-motion"))
    loop.start(robot.obs(0.0))
    loop.step(robot.obs(0.05))
    assert loop.slam is not None and not loop.slam.started
    with pytest.raises(ValueError, match="has not started"):
        loop.set_mode("explore")
    assert loop.kind == "fixate" and loop.explore_choice is None


# ----------------------------------------------------------------------------- on the twin

def _call(st, method, path, body=None):
    c = http.client.HTTPConnection("127.0.0.1", st.port, timeout=30)
    h = {"Authorization": f"Bearer {st.token}"}
    if body is not None:
        h["Content-Type"] = "application/json"
    c.request(method, path, body=None if body is None else json.dumps(body), headers=h)
    r = c.getresponse()
    payload = r.read()
    c.close()
    return r.status, json.loads(payload)


def _wait_twin_time(st, t, timeout=300.0):
    t0 = time.time()
    while st.live.latest() is None or st.live.latest().t < t:
        assert time.time() - t0 < timeout, f"timed out waiting for twin time {t} s"
        time.sleep(0.05)


@pytest.mark.slow
def test_explore_from_the_api_moves_the_head_and_the_state_lists_the_candidates():
    from runtime.apps.station import Station
    from runtime.twin.scenarios import get_scenario
    from wvr.assemble import clicked_target, make_twin

    twin = make_twin()
    twin.configure(get_scenario("workbench-static"), seed=0, seconds=60.0)
    st = Station(twin, lambda obs: clicked_target(twin, seed=0), port=0, seconds=60.0, on_finish=twin.close).open()
    try:
        st.wait_started(600)            # SLAM's kernels compile first when numba's cache is cold
        _wait_twin_time(st, 1.0)
        code, s0 = _call(st, "GET", "/api/state")
        assert code == 200 and s0["localised"] and s0["explore"] is None
        code, reply = _call(st, "POST", "/api/mode", {"mode": "explore"})
        assert code == 200 and reply["accepted"] and reply["mode"] == "explore", reply
        t_set = st.live.latest().t
        _wait_twin_time(st, t_set + 3.0)
        code, s1 = _call(st, "GET", "/api/state")
        ex = s1["explore"]
        assert ex is not None and ex["objective"] == EXPLORE_OBJECTIVE
        assert len(ex["candidates"]) >= 3 and ex["chosen"] is not None
        assert all(math.isfinite(c["score"]) and math.isfinite(c["pose_info"]) and math.isfinite(c["novelty"])
                   for c in ex["candidates"])
        chosen = ex["candidates"][ex["chosen"]]
        # The loop fixates the chosen candidate, and the head went there.
        assert np.allclose(s1["target"], chosen["xyz"], atol=1e-9)
        assert np.abs(np.subtract(s1["joints_deg"], s0["joints_deg"])).max() > 1.0
        # Another mode ends it: the state no longer lists candidates.
        code, reply = _call(st, "POST", "/api/mode", {"mode": "hold"})
        assert code == 200 and reply["mode"] == "hold"
        code, s2 = _call(st, "GET", "/api/state")
        assert s2["explore"] is None and s2["mode"] == "hold"
    finally:
        st.close()
