"""Tests for kinematics.lenses: the table of lens models that camera.toml and the kernels use."""

from dataclasses import fields

import numpy as np
import pytest

from kinematics.camera import LENS_MODELS, CameraFileError, CameraIntrinsics, distort_jacobian
from kinematics.lenses import LENSES, PARAM_ORDER, TERMS, lens_kernel_args, project_point_kernel

# One camera of each model with every one of its terms nonzero.
VALUES = {"k1": -0.21, "k2": 0.07, "k3": -0.011, "k4": 0.002, "p1": 8e-4, "p2": -6e-4, "kd1": 1.5e-6}


def _camera(model: str) -> CameraIntrinsics:
    terms = {t: VALUES[t] for t in LENSES[model].terms}
    return CameraIntrinsics(width=320, height=240, fx=210.0, fy=205.0, cx=161.0, cy=118.5, model=model, **terms)


@pytest.mark.parametrize("model", list(LENSES))
def test_the_compiled_switch_runs_each_models_own_kernel(model):
    cam = _camera(model)
    code, p = lens_kernel_args(cam)
    assert code == LENSES[model].code
    X, Y, Z = 0.13, -0.08, 0.9
    got = project_point_kernel(code, p, X, Y, Z)
    own = LENSES[model].kernel(p, X / Z, Y / Z)
    assert np.isfinite(own).all()
    assert got[:2] == own[:2]
    # The array function goes through the same switch.
    uv, J = distort_jacobian(cam, [[X / Z, Y / Z]])
    assert tuple(uv[0]) == own[:2] and tuple(J[0].ravel()) == own[2:]


@pytest.mark.parametrize("model", list(LENSES))
def test_every_term_of_a_model_moves_its_pixels(model):
    """A term listed for a model but ignored by its kernel (or read from the wrong slot of the
    parameter vector) would leave the pixel where the pinhole puts it."""
    cam = _camera(model)
    base = distort_jacobian(cam, [[0.4, -0.3]])[0]
    for t in LENSES[model].terms:
        moved = CameraIntrinsics(**{**{f.name: getattr(cam, f.name) for f in fields(cam)}, t: 2 * getattr(cam, t)})
        assert not np.allclose(distort_jacobian(moved, [[0.4, -0.3]])[0], base, rtol=0, atol=1e-9), t


def test_the_table_is_what_camera_toml_and_the_kernels_use():
    assert LENS_MODELS == {name: lens.terms for name, lens in LENSES.items()}
    assert [lens.code for lens in LENSES.values()] == list(range(len(LENSES)))
    assert PARAM_ORDER == ("fx", "fy", "cx", "cy") + TERMS
    assert [f.name for f in fields(CameraIntrinsics)][7:] == list(TERMS)
    assert set().union(*(lens.terms for lens in LENSES.values())) == set(TERMS)


def test_a_models_own_rule_is_enforced_through_the_table():
    with pytest.raises(CameraFileError, match=r"\[camera\]\.kd1 = 0\.001 is too large for a 320x240 image"):
        CameraIntrinsics(width=320, height=240, fx=200.0, fy=200.0, cx=160.0, cy=120.0, model="radial-sqrt", kd1=1e-3)
