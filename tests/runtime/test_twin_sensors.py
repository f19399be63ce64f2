"""The twin's sensors as a real wearable gives them: the IMU's errors (BMI088), the camera's
noise, blur and auto-exposure, the operator's clicks, and what a recording carries.

Each effect is checked against an independent measurement: the still mean against the drawn
bias, the noise against the data sheet's density (standard deviation and Allan deviation), the
twin's IMU against its own truth through the drawn errors (and the clock offset found by
search), the image noise by the photon-transfer method (two exposures of one frame), the blur
streak against the image motion predicted by projecting through the true rotation, and the
auto-exposure's lag by fitting its step response."""

import math

import numpy as np
import pytest

from kinematics.camera import default_camera, project
from runtime.twin.image_realism import CAMERA_SENSOR, Exposure, motion_blur
from runtime.twin.imu_errors import BMI088, ImuErrors
from runtime.twin.operator import click, clicked_target, target_in_first_frame
from runtime.twin.render import image_formation
from wvr.cli import main, make_twin

RATE = 200.0
G_CAM = np.array([0.0, 0.0, 9.81])   # specific force at rest, sensor z up


def allan_deviation(x: np.ndarray, m: int) -> float:
    """Overlapping Allan deviation of samples ``x`` (n,) for clusters of m samples."""
    c = np.cumsum(np.r_[0.0, x])
    avg = (c[m:] - c[:-m]) / m
    d = avg[m:] - avg[:-m]
    return float(np.sqrt(0.5 * np.mean(d * d)))


# ------------------------------------------------------------------ IMU model
def test_still_imu_mean_is_the_drawn_bias_and_its_noise_the_data_sheet_density():
    e = ImuErrors.draw(BMI088, RATE, np.random.default_rng(11))
    n = 12000                                   # a minute still
    w, a = e.measure(np.arange(n) / RATE, np.zeros((n, 3)), np.tile(G_CAM, (n, 1)))
    T = n / RATE
    for meas, bias, sigma, density, walk, true in ((w, e.gyro_bias0, e.gyro_sigma, BMI088.gyro_noise_density,
                                                    BMI088.gyro_random_walk, np.zeros(3)),
                                                   (a, e.accel_bias0, e.accel_sigma, BMI088.accel_noise_density,
                                                    BMI088.accel_random_walk, e.M_accel @ G_CAM)):
        tol = 4 * sigma / math.sqrt(n) + 3 * walk * math.sqrt(T)
        np.testing.assert_allclose(meas.mean(axis=0), true + bias, atol=tol)
        assert np.linalg.norm(bias) > 10 * tol          # a bias-free IMU would fail the line above
        np.testing.assert_allclose(meas.std(axis=0), sigma, rtol=0.03)
        np.testing.assert_allclose(sigma, density * math.sqrt(RATE))
        for tau in (0.05, 0.2, 1.0):                    # white noise: ADEV(tau) = N / sqrt(tau)
            adev = [allan_deviation(meas[:, i], int(tau * RATE)) for i in range(3)]
            np.testing.assert_allclose(adev, density / math.sqrt(tau), rtol=0.15)


def test_drawn_biases_are_a_few_mrad_s_and_cm_s2_spread_as_documented():
    draws = [ImuErrors.draw(BMI088, RATE, np.random.default_rng(s)) for s in range(1500)]
    bg = np.array([d.gyro_bias0 for d in draws])
    ba = np.array([d.accel_bias0 for d in draws])
    np.testing.assert_allclose(bg.std(), math.radians(1.0) / 3, rtol=0.05)      # 5.8 mrad/s
    np.testing.assert_allclose(ba.std(), 20e-3 * 9.80665 / 3, rtol=0.05)        # 6.5 cm/s^2
    assert 1e-3 < np.median(np.abs(bg)) < 1e-2 and 1e-2 < np.median(np.abs(ba)) < 1e-1
    dt = np.array([d.time_offset_s for d in draws])
    assert np.all(np.abs(dt) <= 0.005) and dt.std() > 0.0025                      # uniform in +-5 ms
    scale = np.array([np.diag(d.M_gyro) - 1 for d in draws])
    np.testing.assert_allclose(scale.std(), 0.01 / 3, rtol=0.1)
    none = ImuErrors.draw(BMI088.without_scale_and_misalignment(), RATE, np.random.default_rng(0))
    np.testing.assert_array_equal(none.M_gyro, np.eye(3))


def test_bias_random_walk_grows_with_its_density():
    from dataclasses import replace

    spec = replace(BMI088, gyro_noise_density=0.0, accel_noise_density=0.0,
                   gyro_random_walk=1e-3, accel_random_walk=1e-2)   # exaggerated to measure it
    n, T = 1000, 1000 / RATE
    ends_g, ends_a = [], []
    for s in range(100):
        e = ImuErrors.draw(spec, RATE, np.random.default_rng(100 + s))
        e.measure(np.arange(n) / RATE, np.zeros((n, 3)), np.zeros((n, 3)))
        ends_g.append(e.gyro_bias - e.gyro_bias0)
        ends_a.append(e.accel_bias - e.accel_bias0)
    np.testing.assert_allclose(np.var(ends_g), spec.gyro_random_walk ** 2 * T, rtol=0.25)
    np.testing.assert_allclose(np.var(ends_a), spec.accel_random_walk ** 2 * T, rtol=0.25)


@pytest.mark.slow
def test_twin_imu_is_its_truth_through_the_drawn_errors_and_clock_offset():
    """The same run twice, the head shaken by a few rad/s: an ideal, noiseless 1 kHz IMU gives
    the truth (at every physics step, interpolated linearly between them); the real IMU's rows
    minus (M truth(t - offset) + bias(t)) are white noise of the data sheet's sigma, and the
    clock offset found by search over shifts is the drawn one."""
    from kinematics import reference_head
    from runtime.twin.mount import default_shoulder_mount
    from runtime.twin.twin import Twin
    from wvr.cli import wearer_for

    def run(twin):
        rows = [twin.reset("workbench-static", seed=6, seconds=2.0, q0=np.zeros(3)).imu]
        for i in range(1, 60):
            t = i / 30
            rows.append(twin.step([0.2 * math.sin(2 * math.pi * 2 * t), 0.3 * math.sin(2 * math.pi * 1.5 * t), 0]).imu)
        return np.vstack(rows)

    real = make_twin(ideal_camera=True)
    truth_twin = Twin(reference_head(), default_camera(), default_shoulder_mount, wearer_for, imu_rate=1000.0,
                      gyro_noise=0.0, accel_noise=0.0, imu=None, camera_sensor=None)
    try:
        meas = run(real)
        truth = run(truth_twin)
        e = real.imu_errors
    finally:
        real.close()
        truth_twin.close()

    def spline_w(t):
        return np.column_stack([np.interp(t, truth[:, 0], truth[:, 1 + i]) for i in range(3)])

    def spline_f(t):
        return np.column_stack([np.interp(t, truth[:, 0], truth[:, 4 + i]) for i in range(3)])
    bias = np.array([np.r_[bg, ba] for _, bg, ba in e.bias_log])
    np.testing.assert_array_equal([t for t, _, _ in e.bias_log], meas[:, 0])
    ok = (meas[:, 0] > 0.05) & (meas[:, 0] < truth[-1, 0] - 0.05)

    def residual(offset):
        t = meas[ok, 0] - offset
        w = spline_w(t) @ e.M_gyro.T + bias[ok, :3]
        f = spline_f(t) @ e.M_accel.T + bias[ok, 3:]
        return meas[ok, 1:4] - w, meas[ok, 4:7] - f

    r_w, r_f = residual(e.time_offset_s)
    np.testing.assert_allclose(r_w.mean(axis=0), 0, atol=4 * e.gyro_sigma / math.sqrt(ok.sum()))
    np.testing.assert_allclose(r_w.std(axis=0), e.gyro_sigma, rtol=0.12)
    np.testing.assert_allclose(r_f.std(axis=0), e.accel_sigma, rtol=0.12)
    shifts = np.linspace(-0.008, 0.008, 161)
    cost = [np.sum(residual(s)[0] ** 2) for s in shifts]
    assert abs(shifts[int(np.argmin(cost))] - e.time_offset_s) < 0.0005
    # The errors are there: the rows are far from the truth itself.
    assert np.linalg.norm((meas[ok, 1:4] - spline_w(meas[ok, 0])).mean(axis=0)) > 5 * e.gyro_sigma / math.sqrt(ok.sum())


# ------------------------------------------------------------------ camera model
@pytest.fixture(scope="module")
def kitchen():
    t = make_twin()
    t.reset("kitchen-static", seed=4, seconds=1.0)
    yield t
    t.close()


def test_image_noise_matches_the_model_by_photon_transfer(kitchen):
    """Two exposures of one still frame at one gain: half the variance of their difference,
    binned by level, is the model's shot plus read noise (plus 1/12 DN^2 of rounding)."""
    t = kitchen
    t.renderer.update_scene(t.data, camera=t.cam_id)
    rendered = t.renderer.render()
    exp = t.exposure
    g = exp.gain = 2.0
    a = exp.image(rendered, np.zeros(3)).astype(float)
    exp.gain = g
    b = exp.image(rendered, np.zeros(3)).astype(float)
    level, half_var = 0.5 * (a + b), 0.5 * (a - b) ** 2
    checked = 0
    for lo in range(20, 230, 15):
        sel = (level >= lo) & (level < lo + 15)
        if sel.sum() < 3000:
            continue
        model = CAMERA_SENSOR.noise_variance(level[sel].mean(), g) + 1.0 / 12
        np.testing.assert_allclose(half_var[sel].mean(), model, rtol=0.1, err_msg=f"level {lo}")
        checked += 1
    assert checked >= 3
    # Shot noise grows with the signal: the model's slope, not a constant.
    assert CAMERA_SENSOR.noise_variance(200.0, g) > 3 * CAMERA_SENSOR.noise_variance(20.0, g)


def test_blur_streak_is_the_image_motion_predicted_from_the_true_rotation():
    """A bright dot blurred by a head pan's rotation over the exposure: its streak's extent is
    the distance between the dot's projections at the exposure's start and end (the camera's
    true rotation through the lens model, not the blur's homography)."""
    twin = make_twin(ideal_imu=True)
    try:
        obs = twin.reset("workbench-static", seed=0, seconds=1.0, q0=np.zeros(3))
        q = twin.filter.q.copy()
        frames = []
        for i in range(12):                       # pan and tilt at up to about 4 rad/s
            obs = twin.step(q + np.array([0.06, 0.14, 0.0]) * (i + 1))
            phi = twin._rotation_over_half_exposure()
            frames.append((np.linalg.norm(phi) * 2 * twin.camera.fx, phi, twin.ground_truth.T_world_cam[:3, :3]))
    finally:
        twin.close()
    length, phi, R_t = max(frames, key=lambda f: f[0])
    assert length > 10.0 and obs.image.std() > 5
    from scipy.spatial.transform import Rotation

    cam = default_camera()
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    for x0 in ((320, 240), (150, 120), (520, 400)):
        d_world = R_t @ np.array([(x0[0] - cam.cx) / cam.fx, (x0[1] - cam.cy) / cam.fy, 1.0])
        ends = [project(cam, ((R_t @ Rotation.from_rotvec(s * phi).as_matrix()).T @ d_world)[None])[0] for s in (1, -1)]
        predicted = ends[1] - ends[0]
        img = np.zeros((480, 640, 3), np.uint8)
        img[x0[1], x0[0]] = 255
        blurred, length = motion_blur(img, K, phi, CAMERA_SENSOR)
        ys, xs = np.nonzero(blurred[..., 0] > 1.0)
        u = predicted / np.linalg.norm(predicted)
        along = (np.column_stack([xs, ys]) - x0) @ u
        extent = along.max() - along.min()
        # The pixels lit reach past the streak's ends by at most a pixel each (bilinear splats).
        assert extent - 2.0 <= np.linalg.norm(predicted) <= extent + 0.5, (x0, extent, predicted)
        wts = blurred[ys, xs, 0] / blurred[ys, xs, 0].sum()
        mid = wts @ np.column_stack([xs, ys])
        assert np.linalg.norm(mid - 0.5 * (ends[0] + ends[1])) < 0.3        # centred on the stamp
        axis = np.linalg.svd((np.column_stack([xs, ys]) - mid) * np.sqrt(wts)[:, None])[2][0]
        assert abs(axis @ u) > math.cos(math.radians(4.0))          # along the predicted motion


def test_auto_exposure_follows_a_brightness_step_with_its_lag():
    """A scene that halves in brightness: the output mean halves, then the gain recovers it to
    the target with the controller's time constant (fitted to the step response)."""
    f = image_formation(default_camera())
    exp = Exposure(CAMERA_SENSOR, f, 1 / 30, np.random.default_rng(0))
    rng = np.random.default_rng(1)
    base = np.clip(100 + 30 * rng.standard_normal((480, 640, 3)), 0, 255)
    means = []
    for k in range(120):
        scene = base if k < 30 else 0.5 * base
        means.append(exp.image(scene.astype(np.uint8), np.zeros(3)).mean())
    means = np.array(means)
    target = CAMERA_SENSOR.target_mean_dn
    assert abs(means[29] - target) < 2.0                       # converged
    assert means[30] < 0.6 * target                            # the step shows at once
    assert abs(means[-1] - target) < 2.0                       # and is compensated
    # log(target / mean) decays as exp(-t / tau) from the frame after the step.
    k = np.arange(31, 75)
    y = np.log(target / means[k])
    slope = np.polyfit((k - 31) / 30, np.log(y), 1)[0]
    np.testing.assert_allclose(-1 / slope, CAMERA_SENSOR.ae_time_constant_s, rtol=0.1)


def test_dimming_raises_the_gain_and_holds_the_brightness():
    from dataclasses import replace

    from runtime.twin.recorder import scripted_frames
    from runtime.twin.scenarios import get_scenario

    twin = make_twin(ideal_imu=True)
    try:
        obs = twin.reset(replace(get_scenario("office-static"), dim_to=0.3), seed=0, seconds=3.0)
        means = [float(o.image.mean()) for o in scripted_frames(twin, obs)]
        gains = [g for g, _ in twin.exposure.log]
    finally:
        twin.close()
    assert gains[-1] > 1.5 * gains[0]
    assert abs(means[-1] - means[0]) < 0.25 * means[0]


# ------------------------------------------------------------------ operator and recordings
def test_clicks_are_two_to_three_pixels_off_on_half_pixels():
    rng = np.random.default_rng(5)
    uv = rng.uniform(50, 400, (4000, 2))
    c = click(uv, 2.5, rng, 640, 480)
    err = np.linalg.norm(c - uv, axis=1)
    assert err.min() > 2.0 - 0.36 and err.max() < 3.0 + 0.36      # 0.8..1.2 x 2.5, then rounding
    assert abs(err.mean() - 2.5) < 0.05
    np.testing.assert_array_equal(c * 2, np.round(c * 2))
    np.testing.assert_array_equal(click(uv, 0.0, rng, 640, 480), uv)
    with pytest.raises(ValueError, match="0 or more"):
        click(uv, -1.0, rng, 640, 480)


def test_clicked_target_is_seeded_by_the_run_and_off_the_truth(kitchen):
    exact = target_in_first_frame(kitchen)
    a, b = clicked_target(kitchen), clicked_target(kitchen)
    np.testing.assert_array_equal(a.uv, b.uv)
    np.testing.assert_array_equal(a.xyz, exact.xyz)
    err = np.linalg.norm(a.uv - exact.uv, axis=1)
    assert np.all((err > 1.6) & (err < 3.4))


@pytest.mark.slow
def test_recording_carries_its_head_clicked_target_and_truth_files(tmp_path):
    from kinematics import reference_head
    from kinematics.geometry import load_head
    from kinematics.tomlfile import read_toml
    from runtime.sequence import load_target, open_sequence

    out = tmp_path / "seq"
    assert main(["sim", "record", "--scenario", "office-far-target", "--seconds", "0.5", "--seed", "3",
                 "--scene-seed", "8", "--out", str(out)]) == 0
    seq = open_sequence(out)
    assert load_head(out / "head.toml").to_dict() == reference_head().to_dict()
    truth = load_target(out / "target_truth.toml")
    err = np.linalg.norm(seq.target.uv - truth.uv, axis=1)
    assert np.all((err > 1.6) & (err < 3.4))
    twin_toml = read_toml(out / "twin.toml", ValueError, "twin.toml")
    assert twin_toml["seeds"] == {"run": 3, "scene": 8, "note": twin_toml["seeds"]["note"]}
    imu_truth = read_toml(out / "imu_truth.toml", ValueError, "imu_truth.toml")
    bias = np.loadtxt(out / "imu_bias.txt")
    np.testing.assert_array_equal(bias[:, 0], seq.imu.t)
    np.testing.assert_allclose(bias[0, 1:4], imu_truth["bias"]["gyro_initial_rad_s"], rtol=1e-8)
    exposure = np.loadtxt(out / "exposure_truth.txt")
    np.testing.assert_allclose(exposure[:, 0], seq.timestamps, atol=1e-9)
    # The ideal sensors and exact pixels: today's recordings.
    ideal = tmp_path / "ideal"
    assert main(["sim", "record", "--scenario", "office-far-target", "--seconds", "0.2", "--ideal-imu",
                 "--ideal-camera", "--click-error", "0", "--out", str(ideal)]) == 0
    np.testing.assert_array_equal(load_target(ideal / "target.toml").uv, load_target(ideal / "target_truth.toml").uv)
    assert not (ideal / "imu_truth.toml").exists() and not (ideal / "exposure_truth.txt").exists()


@pytest.mark.parametrize("args,message", [(["--click-error", "-1"], "--click-error -1"),
                                          (["--click-error", "nan"], "--click-error nan"),
                                          (["--scene-seed", "-2"], "--scene-seed -2"),
                                          (["--seed", "-1"], "--seed -1")])
def test_bad_record_options_are_one_line_errors(tmp_path, capsys, args, message):
    out = tmp_path / "never"
    # Refused while the options are parsed (argparse's exit 2), naming the option and the value.
    with pytest.raises(SystemExit) as e:
        main(["sim", "record", "--scenario", "kitchen-static", "--out", str(out), *args])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    flag, value = message.split()
    assert f"argument {flag}: '{value}'" in err and "\n" not in err
    assert not out.exists()
