"""The SLAM's settings as frozen groups, and the one mapping that keeps the old flat names
working as keywords and refuses them as attributes (runtime/slam/config.py)."""

from dataclasses import FrozenInstanceError, replace

import pytest

from runtime.slam.config import DEFAULT_CONFIG, MAP_FLAT, SLAM_FLAT, MapSettings, SlamConfig, with_overrides


def test_a_flat_override_lands_in_its_group_and_keeps_the_other_groups():
    s = replace(MapSettings().with_measure(30), use_imu=False, ransac_confidence=0.95, features="particles")
    assert s.imu.use_imu is False and s.ransac.confidence == 0.95
    assert s.features == "particles"
    assert (s.measure.measure_max, s.measure.visible_min) == (30, 24)      # with_measure's group survives
    assert s.imu.imu_biases is True and s.ransac.threshold_px == 2.0       # the rest of each group unchanged
    assert with_overrides(MapSettings(), reloc_every=7).relocalisation.reloc_every == 7
    assert MapSettings(use_imu=False) == replace(MapSettings(), imu=replace(MapSettings().imu, use_imu=False))


def test_the_filter_s_config_maps_its_flat_names_too():
    c = replace(DEFAULT_CONFIG, time_offset0=0.02, adapt_onset=False, sigma_pixel=2.0)
    assert (c.imu.time_offset0, c.impulses.adapt_onset, c.sigma_pixel) == (0.02, False, 2.0)
    assert c.motion == DEFAULT_CONFIG.motion and c.guard == DEFAULT_CONFIG.guard
    assert SlamConfig(sigma_a=2.5).motion.sigma_a == 2.5


def test_every_flat_name_lists_its_group_s_value_and_is_refused_as_an_attribute():
    s, c = MapSettings(reloc_every=7), SlamConfig(sigma_a=2.5)
    for obj, table in ((s, MAP_FLAT), (c, SLAM_FLAT)):
        values = obj.flat()
        for name, (group, field) in table.items():
            assert values[name] == getattr(getattr(obj, group), field)
            moved = rf"^{type(obj).__name__}\.{name} moved: read settings\.{group}\.{field}$"
            with pytest.raises(AttributeError, match=moved):
                getattr(obj, name)
    assert (s.flat()["reloc_every"], c.flat()["sigma_a"]) == (7, 2.5)
    # a renamed one names its new field; a name that never was one is the usual error
    with pytest.raises(AttributeError, match="ransac_confidence moved: read settings.ransac.confidence"):
        s.ransac_confidence
    with pytest.raises(AttributeError, match="has no attribute 'use_imus'$"):
        s.use_imus
    assert not hasattr(s, "use_imu") and s.features == "inverse-depth" and c.sigma_pixel == 1.0
    # every old field, plus the top-level ones (93), the guided search's three (measure.guide_*),
    # its rescue's area (measure.rescue_area_px), the depth prior's spread
    # (inverse_depth.scene_depth_spread) and its two relative widths (inverse_depth.scene_relative_width,
    # inverse_depth.two_view_relative_width) and the IMU's hand-over's four (imu.imu_handover,
    # imu.handover_*) and its gravity's prior (imu.handover_gravity_sigma)
    assert len(MAP_FLAT) + 2 == 93 + 3 + 1 + 1 + 2 + 4 + 1 and len(SLAM_FLAT) + 1 == 29
    assert set(MapSettings().flat()) == set(MAP_FLAT) | {"features", "warp"}


def test_unknown_names_and_bad_values_are_refused_naming_the_place():
    with pytest.raises(TypeError, match="no setting 'use_imus'.*imu"):
        MapSettings(use_imus=False)
    with pytest.raises(ValueError, match="MapSettings.reloc_sigma_m"):
        MapSettings(reloc_sigma_m=-1.0)
    with pytest.raises(ValueError, match="SlamConfig.time_offset0"):
        SlamConfig(time_offset0=float("nan"))
    with pytest.raises(ValueError, match="visible_min"):
        MapSettings(visible_min=70)
    with pytest.raises(FrozenInstanceError):
        MapSettings().imu.use_imu = False
