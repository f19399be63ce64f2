"""The criteria against analytic cases, the layout rule, the workload, and mj_inverse."""

import math
import tomllib
import xml.etree.ElementTree as ET
from dataclasses import replace

import mujoco
import numpy as np
import pytest

from design import criteria as C
from design.layout import head_from_variables, variables_from_head
from design.sweep_file import CRITERIA, SweepFileError, default_sweep_text, load_sweep, spec_from_dict
from design.workload import Workload, build_workload
from kinematics import Part, forward_kinematics, reference_head
from kinematics.dynamics import GRAVITY
from kinematics.mjcf import head_body

SPEC = load_sweep()


def small_workload_spec():
    return replace(SPEC.workload, saccade_amplitudes_deg=(10.0,), walk_seconds=0.5, rate_hz=50.0)


def static_workload(n=1, gravity=(0, 0, -GRAVITY)):
    z = np.zeros((n, 3))
    return Workload(q=z, qd=z, qdd=z, gravity_mount=np.tile(gravity, (n, 1)), omega_mount=z, alpha_mount=z,
                    accel_mount=z, dt=np.full(n, 0.01), segment=np.zeros(n, int), labels=("hold",))


def test_camera_on_an_axis_has_radius_zero():
    h = reference_head()   # its optical centre is on the cyclotorsion axis
    assert C.radius_cyclotorsion_mm(h) == pytest.approx(0.0, abs=1e-12)
    # Put the optical centre on the pan axis too: radius 0 about pan, and about elevation it is
    # the height above the elevation axis.
    pose = forward_kinematics(h, np.zeros(3))
    lift = replace(h.camera, origin_m=(h.camera.origin_m[0] - pose.p_mount_cam[0], 0.0, 0.0))
    h2 = replace(h, camera=lift)
    assert C.radius_pan_mm(h2) == pytest.approx(0.0, abs=1e-9)
    assert C.radius_elevation_mm(h2) == pytest.approx(1000 * (pose.p_mount_cam[2] - h.joints[0].origin_m[2]), rel=1e-12)


def test_point_mass_static_torque_is_m_g_r():
    """A heavy part of negligible size at lever r from the horizontal elevation axis: tau = m g r."""
    h = reference_head()
    m, r = 0.05, 0.04
    tiny = (1e-6, 1e-6, 1e-6)
    parts = tuple(replace(p, mass_kg=1e-9, size_m=tiny, center_m=(0.0, 0.0, 0.0)) for p in h.parts)
    parts += (Part("weight", "elevation", (r, 0.0, 0.0), tiny, m, "bracket"),)
    h = replace(h, parts=parts)
    w = static_workload()
    assert C.max_torque_nm(h, w) == pytest.approx(m * GRAVITY * r, rel=1e-6)
    assert C.integrated_torque(h, w) == pytest.approx((m * GRAVITY * r) ** 2 * 0.01, rel=1e-5)


def test_layout_round_trip_and_rules():
    rng = np.random.default_rng(0)
    for _ in range(20):
        x = rng.uniform(SPEC.xl, SPEC.xu)
        h = head_from_variables(x, SPEC)
        np.testing.assert_allclose(variables_from_head(h, SPEC), x, atol=1e-15)
        # The camera's optic axis is the cyclotorsion axis, at any layout.
        assert np.linalg.norm(np.cross(h.camera.forward, h.joints[2].axis)) == 0
        assert all(math.degrees(j.range_rad[1] - j.range_rad[0]) == pytest.approx(SPEC.range_deg) for j in h.joints)
    with pytest.raises(ValueError, match="12 variables"):
        head_from_variables(np.zeros(5), SPEC)


def test_workload_respects_the_controlled_motion_limit_and_servo():
    spec = small_workload_spec()
    w = build_workload(head_from_variables((SPEC.xl + SPEC.xu) / 2, SPEC), spec)
    saccade = w.segment < len(w.labels) - 1
    # The gaze moves at the 30 deg/s limit; individual joints near it (cyclotorsion can differ).
    assert np.abs(w.qd[saccade, :2]).max() == pytest.approx(math.radians(30), rel=0.02)
    assert np.abs(w.qd).max() < 10.0
    walk = ~saccade
    assert np.linalg.norm(w.gravity_mount[walk], axis=1) == pytest.approx(np.full(walk.sum(), GRAVITY))
    assert np.abs(w.omega_mount[walk]).max() > 0.1


def test_torques_match_mj_inverse_on_workload_states():
    """The criteria's torques against MuJoCo's inverse dynamics, mount moving, to 1e-6 N m."""
    rng = np.random.default_rng(1)
    head = head_from_variables(rng.uniform(SPEC.xl, SPEC.xu), SPEC)
    w = build_workload(head, small_workload_spec())
    tau = C.workload_torques(head, w)
    root = ET.Element("mujoco")
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    ET.SubElement(root, "option", gravity="0 0 0")  # gravity enters through the base acceleration below
    base = ET.SubElement(ET.SubElement(root, "worldbody"), "body", name="wearer")
    ET.SubElement(base, "freejoint")
    ET.SubElement(base, "inertial", pos="0 0 0", mass="1", diaginertia="0.01 0.01 0.01")
    base.append(head_body(head))
    model = mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"))
    data = mujoco.MjData(model)
    for k in rng.choice(len(w.q), 60, replace=False):
        data.qpos[:7] = [0, 0, 0, 1, 0, 0, 0]   # the base frame is the mount frame at this instant
        data.qpos[7:] = w.q[k]
        data.qvel[:3] = 0
        data.qvel[3:6] = w.omega_mount[k]
        data.qvel[6:] = w.qd[k]
        # Mount acceleration minus gravity is what the parts feel (equivalence principle).
        data.qacc[:3] = w.accel_mount[k] - w.gravity_mount[k]
        data.qacc[3:6] = w.alpha_mount[k]
        data.qacc[6:] = w.qdd[k]
        mujoco.mj_inverse(model, data)
        np.testing.assert_allclose(tau[k], data.qfrc_inverse[6:], atol=1e-6)


def test_bad_sweep_files_name_the_field():
    base = tomllib.loads(default_sweep_text())

    def bad(mutate, *needles):
        d = tomllib.loads(default_sweep_text())
        mutate(d)
        with pytest.raises(SweepFileError) as e:
            spec_from_dict(d, "s.toml")
        msg = str(e.value)
        assert "\n" not in msg and msg.startswith("s.toml")
        for n in needles:
            assert n in msg, msg

    bad(lambda d: d["sweep"].update(range_deg=170), "[sweep].range_deg", "160")
    bad(lambda d: d["bounds"].update(camera=[[0, 10], [0, 1], [0, 1]]), "[bounds].camera", "millimetres")
    bad(lambda d: d["bounds"].update(camera=[[0.1, 0.0], [0, 0.1], [0, 0.1]]), "min < max")
    bad(lambda d: d["decision"].update(weights=[1, 1]), "[decision].weights", "7")
    bad(lambda d: d["sweep"].update(algorithm="nsga2"), "[sweep].algorithm")
    bad(lambda d: d["workload"].update(speed=3), "unknown key 'speed'")
    bad(lambda d: d.update(extra={}), "unknown section [extra]")
    assert spec_from_dict(base).digest() == SPEC.digest()
    assert tuple(CRITERIA)[0] == "working_volume_cm3"
