"""head.toml: round trip, the reference head, and one-line errors for bad files."""

import math

import numpy as np
import pytest
import tomli_w

from kinematics import HeadFileError, load_head, reference_head, save_head
from kinematics.geometry import HeadGeometry


def test_reference_head_is_the_papers():
    h = reference_head()
    assert [j.name for j in h.joints] == ["elevation", "pan", "cyclotorsion"]
    for i in range(3):
        s = h.servo_of(i)
        assert s.name == "HS-50"
        assert math.degrees(s.travel_rad) == pytest.approx(160)
        assert s.max_speed_rad_s == 10.0 and s.stall_torque_nm == 0.06 and s.mass_kg == 0.006
        assert s.volume_m3 == pytest.approx(6e-6, rel=0.05)
    assert np.linalg.norm(np.cross(h.camera.forward, h.joints[2].axis)) == 0


def test_round_trip(tmp_path):
    h = reference_head()
    save_head(h, tmp_path / "head.toml")
    h2 = load_head(tmp_path / "head.toml")
    assert h2 == h


def test_custom_servo_round_trip(tmp_path):
    d = reference_head().to_dict()
    d["servos"] = {"HS-40": {"travel_deg": 150.0, "max_speed_rad_s": 8.0, "stall_torque_nm": 0.04,
                             "mass_kg": 0.0045, "size_m": [0.02, 0.0086, 0.018]}}
    d["joints"]["cyclotorsion"]["servo"] = "HS-40"
    d["joints"]["cyclotorsion"]["range_deg"] = [-75.0, 75.0]
    h = HeadGeometry.from_dict(d)
    save_head(h, tmp_path / "h.toml")
    assert load_head(tmp_path / "h.toml") == h
    assert h.servo_of("cyclotorsion").stall_torque_nm == 0.04


def _bad(tmp_path, mutate):
    d = reference_head().to_dict()
    mutate(d)
    p = tmp_path / "head.toml"
    p.write_text(tomli_w.dumps(d))
    with pytest.raises(HeadFileError) as e:
        load_head(p)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(str(p))
    return msg


def test_bad_files_give_one_line_errors_naming_field_and_fix(tmp_path):
    m = _bad(tmp_path, lambda d: d["joints"]["pan"].update(axsi=[0, 0, 1]))
    assert "unknown key 'axsi'" in m and "joints.pan" in m and "allowed keys" in m
    m = _bad(tmp_path, lambda d: d["joints"]["pan"].update(axis=[0, 0, 2]))
    assert "joints.pan.axis" in m and "not a unit vector" in m and "use [0.0, 0.0, 1.0]" in m
    m = _bad(tmp_path, lambda d: d["joints"]["elevation"].update(range_deg=[-90, 90]))
    assert "joints.elevation.range_deg" in m and "160" in m and "narrow it" in m
    m = _bad(tmp_path, lambda d: d["parts"][0].update(mass_kg=-0.006))
    assert "mass_kg" in m and "negative" in m and "elevation_servo" in m
    m = _bad(tmp_path, lambda d: d["camera"].update(forward=[0.0, 1.0, 0.0], right=[1.0, 0.0, 0.0]))
    assert "camera.forward must be parallel" in m
    m = _bad(tmp_path, lambda d: d["joints"]["pan"].update(servo="HS-999"))
    assert "HS-999" in m and "not a known servo" in m
    m = _bad(tmp_path, lambda d: d["joints"].pop("pan"))
    assert "missing key 'pan'" in m
    m = _bad(tmp_path, lambda d: d["parts"].__setitem__(slice(None), [p for p in d["parts"] if p["link"] != "pan"]))
    assert "link 'pan' carries no mass" in m
    m = _bad(tmp_path, lambda d: d["joints"]["pan"].update(origin_m=[0, 0]))
    assert "joints.pan.origin_m" in m and "3 numbers" in m


def test_not_toml_and_missing_file(tmp_path):
    p = tmp_path / "x.toml"
    p.write_text("this is = = not toml")
    with pytest.raises(HeadFileError, match="not valid TOML"):
        load_head(p)
    with pytest.raises(HeadFileError, match="no such file"):
        load_head(tmp_path / "nope.toml")


def test_messages_stay_short_and_name_the_real_problem(tmp_path):
    d = reference_head().to_dict()
    d["joints"]["pan"]["origin_m"] = [0.0] * 200_000        # a huge array typed by mistake
    path = tmp_path / "huge.toml"
    path.write_text(tomli_w.dumps(d))
    with pytest.raises(HeadFileError) as e:
        load_head(path)
    msg = str(e.value)
    assert len(msg) < 300 and "joints.pan.origin_m" in msg and "200000" in msg
    d = reference_head().to_dict()
    d["parts"][0]["mass_kg"] = math.inf
    with pytest.raises(HeadFileError) as e:
        HeadGeometry.from_dict(d)
    assert "not a finite number" in str(e.value) and "negative" not in str(e.value)
    d["parts"][0]["mass_kg"] = -0.1
    with pytest.raises(HeadFileError, match="is negative"):
        HeadGeometry.from_dict(d)
    d = reference_head().to_dict()
    d["servos"] = {"HS-40": {"travel_deg": [1, 2], "max_speed_rad_s": 8.0, "stall_torque_nm": 0.04,
                             "mass_kg": 0.0045, "size_m": [0.02, 0.0086, 0.018]}}
    with pytest.raises(HeadFileError, match="servos.HS-40: every value must be a number"):
        HeadGeometry.from_dict(d)
