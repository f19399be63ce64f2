"""The station's page in a real headless Chromium (Debian's, through Playwright) on the twin:
the page refuses without the token and loads with it; the 3D view and the camera image appear
and the image updates; a click on a feature in the 3D view, and one on the camera view, start a
saccade that the twin's truth confirms (the true optic axis turns onto the feature's true
position); a label placed on the page shows in the camera view; the wearer's page shows the
prompt.

The camera-view clicks use the page's camera pane alone (``#camera``): the same pane, without the
3D view beside it, whose software-rendered WebGL on this 2-core test machine would otherwise take
most of the browser's time (on an operator's machine with a GPU it does not)."""

import json
import math
import time

import cv2
import numpy as np
import pytest

from runtime.apps.station import Station
from runtime.apps.station.geometry import world_to_pixels
from runtime.twin.scenarios import get_scenario
from wvr.assemble import clicked_target, make_twin

pytest.importorskip("playwright")
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def station():
    twin = make_twin()
    twin.configure(get_scenario("workbench-static"), seed=0, seconds=120.0)
    st = Station(twin, lambda obs: clicked_target(twin, seed=0), port=0, truth=twin, seconds=120.0,
                 on_finish=twin.close).open()
    st.wait_started()
    st.twin = twin
    st.corners_true = twin.landmarks()["target_corners"]        # scoring only
    yield st
    st.close()


@pytest.fixture(scope="module")
def browser():
    from runtime.apps.station.browser import headless_browser

    with headless_browser() as ctx:
        yield ctx


def camera_pixels(page) -> np.ndarray:
    """The camera pane as the page shows it, (480, 640, 3) BGR (its CSS size is the image's)."""
    return cv2.imdecode(np.frombuffer(page.locator("#camera").screenshot(), np.uint8), cv2.IMREAD_COLOR)


def wait_for(cond, timeout=60.0, what="condition"):
    t0 = time.time()
    while not cond():
        assert time.time() - t0 < timeout, f"timed out waiting for {what}"
        time.sleep(0.05)


def settle(st, t=1.5):
    wait_for(lambda: st.live.latest().t >= t, 120, f"twin time {t} s")


def axis_error_deg(st, i, p_true):
    """Angle (deg) between the true optic axis at period i and the true point."""
    T = st.live.run.T_true[i]
    d = p_true - T[:3, 3]
    return math.degrees(math.acos(np.clip(T[:3, 2] @ d / np.linalg.norm(d), -1, 1)))


def known_features(st):
    v = st.live.latest().view
    return [(int(i), p) for i, p, k in zip(v.ids, v.xyz, v.known) if k]


def true_point(st, xyz):
    c = st.corners_true
    return c[np.argmin(np.linalg.norm(c - xyz, axis=1))]


def event_for(st, source, action, n0):
    evs = [e for e in st.live.run.events[n0:] if e.source == source and e.action == action]
    return evs[-1] if evs else None


def wait_still(st, periods=5):
    """Until the head has been commanded (nearly) still for a few periods (a saccade landed)."""
    still, seq = 0, -1
    t0 = time.time()
    while still < periods:
        assert time.time() - t0 < 120, "the head never came to rest"
        s = st.live.wait_newer(seq, 5.0)
        if s is None:
            continue
        seq = s.seq
        still = still + 1 if np.degrees(np.abs(s.cmd_qd)).max() < 0.5 else 0


def check_saccade_lands(st, ev, feature_xyz):
    """The truth after an accepted fixate event: off the point when clicked, on it after."""
    p = true_point(st, feature_xyz)
    # The period that applied it is recorded just after the event is.
    wait_for(lambda: len(st.live.run.T_true) and st.live.run.times[len(st.live.run.T_true) - 1] >= ev.t, 60,
             "the clicked period's record")
    i0 = int(np.searchsorted(st.live.run.times, ev.t))
    e0 = axis_error_deg(st, i0, p)
    wait_for(lambda: st.live.run.times[len(st.live.run.T_true) - 1] >= ev.t + 2.5, 120,
             "2.5 s of twin time after the click")
    i1 = int(np.searchsorted(st.live.run.times, ev.t + 2.5))
    e1 = axis_error_deg(st, i1, p)
    assert e0 > 2.0, f"the feature was already fixated ({e0:.1f} deg)"
    assert e1 < 1.5 and e1 < 0.3 * e0, (e0, e1)
    # And it moved there at the controlled-motion limit: the joints' commanded rates stayed within it.
    rates = np.array([r.cmd_rate for r in st.live.loop.log.rows[i0:i1]])
    assert np.degrees(np.abs(rates)).max() <= 30.0 + 1e-6


def test_the_page_refuses_without_the_token(station, browser):
    page = browser.new_page()
    for url in (station.public_url, station.public_url + "?token=not-the-token", station.public_url + "viser/",
                station.public_url + "wearer"):
        r = page.goto(url)
        assert r.status == 401, url
        assert "needs its token" in page.content()
    page.close()


def test_the_page_loads_with_the_token_and_the_images_update(station, browser):
    page = browser.new_page()
    r = page.goto(station.url)
    assert r.status == 200 and page.url == station.public_url           # the token left the address bar
    page.wait_for_function("window.station && window.station.frames >= 2", timeout=120_000)
    seq0 = page.evaluate("window.station.seq")
    page.wait_for_function(f"window.station.seq > {seq0}", timeout=60_000)
    # The camera view shows the twin's image: not blank, and it changes (time moves on).
    # What the page shows (a worker draws the canvas): the pane's pixels, 1:1 with the image's.
    first = camera_pixels(page)
    assert first.shape == (480, 640, 3) and first.std() > 20
    seq1 = page.evaluate("window.station.seq")
    page.wait_for_function(f"window.station.seq > {seq1}", timeout=60_000)
    assert np.abs(camera_pixels(page).astype(int) - first).mean() > 0.5
    # The 3D view: viser's canvas in the frame, connected through the gate.
    frame = page.frame_locator("#view3d")
    frame.locator("canvas").first.wait_for(timeout=120_000)
    wait_for(lambda: len(station.view.server.get_clients()) >= 1, 60, "the 3D view's client")
    u0 = station.view.updates
    wait_for(lambda: station.view.updates > u0, 30, "a 3D view update")
    page.close()


def test_a_click_on_a_feature_in_the_3d_view_starts_a_saccade(station, browser):
    settle(station)
    wait_still(station)
    page = browser.new_page()
    page.goto(station.url)
    frame = page.frame_locator("#view3d")
    canvas = frame.locator("canvas").first
    canvas.wait_for(timeout=120_000)
    wait_for(lambda: len(station.view.server.get_clients()) >= 1, 60, "the 3D view's client")
    client = list(station.view.server.get_clients().values())[-1]
    fid, xyz = known_features(station)[0]
    wait_for(lambda: fid in station.view._markers, 30, "the feature's marker")
    # Look at the feature from 0.5 m (so its marker is under the canvas centre), then click there.
    client.camera.up_direction = (0.0, 0.0, 1.0)
    client.camera.position = xyz + np.array([0.0, -0.35, 0.35])
    client.camera.look_at = xyz
    time.sleep(2.0)
    box = canvas.bounding_box()
    n0 = len(station.live.run.events)
    page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    wait_for(lambda: event_for(station, "3d", "fixate", n0) is not None, 60, "the 3D click's action")
    ev = event_for(station, "3d", "fixate", n0)
    assert ev.accepted and f"'feature': {fid}" in ev.detail, (ev.detail, ev.reason)
    page.close()
    check_saccade_lands(station, ev, xyz)


def test_a_click_on_the_camera_view_starts_a_saccade(station, browser):
    settle(station)
    wait_still(station)
    page = browser.new_page()
    page.goto(station.url + "#camera")
    page.wait_for_function("window.station && window.station.frames >= 2", timeout=120_000)
    # The corner farthest from where the head looks now, at its pixel in the current view.
    snap = station.live.latest()
    feats = known_features(station)
    T = snap.view.T_world_cam
    off = [math.degrees(math.acos(np.clip(T[:3, 2] @ (p - T[:3, 3]) / np.linalg.norm(p - T[:3, 3]), -1, 1)))
           for _, p in feats]
    fid, xyz = feats[int(np.argmax(off))]
    uv = world_to_pixels(station.live.camera, T, xyz[None])[0]
    box = page.locator("#camera").bounding_box()
    n0 = len(station.live.run.events)
    page.mouse.click(box["x"] + uv[0] * box["width"] / 640, box["y"] + uv[1] * box["height"] / 480)
    wait_for(lambda: event_for(station, "camera-view", "fixate", n0) is not None, 60, "the camera-view click")
    ev = event_for(station, "camera-view", "fixate", n0)
    assert ev.accepted, ev.reason
    page.close()
    check_saccade_lands(station, ev, xyz)


def test_a_label_placed_on_the_page_shows_in_the_camera_view(station, browser):
    settle(station)
    wait_still(station)
    page = browser.new_page()
    page.goto(station.url + "#camera")
    page.wait_for_function("window.station && window.station.frames >= 2", timeout=120_000)
    fid, xyz = known_features(station)[1]

    def magenta_near(uv):
        shot = camera_pixels(page)
        x0, y0 = int(uv[0]) - 9, int(uv[1]) - 9
        d = shot[y0:y0 + 19, x0:x0 + 19].astype(int)
        return int(((d[..., 2] > 190) & (d[..., 1] < 60) & (d[..., 0] > 190)).sum())

    uv = world_to_pixels(station.live.camera, station.live.latest().view.T_world_cam, xyz[None])[0]
    assert magenta_near(uv) < 3
    page.check("input[name=tool][value=label]")
    page.fill("#text", "valve")
    box = page.locator("#camera").bounding_box()
    n0 = len(station.live.run.events)
    page.mouse.click(box["x"] + uv[0] * box["width"] / 640, box["y"] + uv[1] * box["height"] / 480)
    wait_for(lambda: event_for(station, "camera-view", "label", n0) is not None, 60, "the label action")
    assert event_for(station, "camera-view", "label", n0).accepted
    label = station.live.run.labels[-1]
    assert label.text == "valve" and np.linalg.norm(label.xyz - xyz) < 1e-3
    seq = page.evaluate("window.station.seq")
    page.wait_for_function(f"window.station.seq > {seq + 1}", timeout=60_000)
    # The ring is drawn where the label's point projects in the frame on the canvas.
    s = station.live.latest()
    uv_now = world_to_pixels(station.live.camera, s.view.T_world_cam, label.xyz[None])[0]
    assert magenta_near(uv_now) > 15
    page.close()


def test_the_wearers_page_shows_the_prompt(station, browser):
    page = browser.new_page()
    page.goto(station.wearer_url)
    assert station.token not in page.content()                 # the wearer's page holds its own token only
    T = station.live.latest().view.T_world_cam
    behind = (T[:3, 3] - 2.0 * T[:3, 2] + np.array([0.0, 0.0, 0.3])).tolist()
    res = page.evaluate("""async (body) => {
        const r = await fetch('/api/fixate', {method: 'POST', headers: {'Authorization': 'Bearer ' + %s,
            'Content-Type': 'application/json'}, body: JSON.stringify(body)});
        return [r.status, await r.json()]; }""" % json.dumps(station.token), {"xyz": behind})
    assert res[0] == 422 and res[1]["prompt"]
    page.wait_for_function("window.wearer.prompts.length > 0", timeout=30_000)
    assert page.locator("#prompt").inner_text().startswith("Please ")
    # With the token it holds, the wearer's page can neither stop nor steer the head.
    n = len(station.live.run.events)
    codes = page.evaluate("""async (token) => Promise.all(["stop", "fixate", "mode"].map(async (k) =>
        (await fetch('/api/' + k, {method: 'POST', headers: {'Authorization': 'Bearer ' + token,
            'Content-Type': 'application/json'}, body: '{"feature": 0, "mode": "hold"}'})).status))""",
                          station.wearer_token)
    assert codes == [403, 403, 403] and len(station.live.run.events) == n and not station.live.latest().estop
    page.close()
