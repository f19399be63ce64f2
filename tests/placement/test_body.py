"""Tests for placement.body's face frames: every face, degenerate ones too, gets a unit normal."""

import numpy as np
import pytest

from placement.body import Body, BodyError, Motion, make_body

BODY = make_body()


def _with_faces(body: Body, vertices: np.ndarray, faces: np.ndarray, face_segment: np.ndarray) -> Body:
    return Body(vertices, faces, face_segment, body.joints)


def _collapsed(body: Body, f: int) -> Body:
    """The body with face f's third vertex moved onto its first: zero area, as exports leave."""
    faces = body.faces.copy()
    faces[f, 2] = faces[f, 0]
    return _with_faces(body, body.vertices, faces, body.face_segment)


def test_a_zero_area_face_takes_its_neighbours_normal_and_the_rest_stay_as_they_were():
    f = 100
    c0, n0 = BODY.face_frames()
    body = _collapsed(BODY, f)
    c, n = body.face_frames()
    assert np.isfinite(n).all() and np.isfinite(c).all()
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    others = np.arange(len(n)) != f
    assert np.array_equal(n[others], n0[others])            # the other faces to the bit
    # The body surface is smooth there: the neighbours' mean normal is close to the face's own.
    assert n[f] @ n0[f] > 0.9


def test_a_collinear_face_is_degenerate_too():
    f = 100
    a, b = BODY.faces[f, :2]
    vertices = np.vstack([BODY.vertices, 0.5 * (BODY.vertices[a] + BODY.vertices[b])])
    faces = BODY.faces.copy()
    faces[f] = [a, b, len(BODY.vertices)]
    _, n0 = BODY.face_frames()
    _, n = _with_faces(BODY, vertices, faces, BODY.face_segment).face_frames()
    assert n[f] @ n0[f] > 0.9


def test_degenerate_faces_get_frames_over_a_motion():
    f = 100
    body = _collapsed(BODY, f)
    rv = np.zeros((3, 16, 3))
    rv[1:, 0, 2] = [0.3, 0.6]                                 # the pelvis (and all) turning about z
    c, n = body.face_frames(Motion("turn", np.arange(3.0), rv, np.zeros((3, 3))))
    assert c.shape == n.shape == (3, len(body.faces), 3)
    assert np.isfinite(n).all()
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-12)
    _, n_rest = body.face_frames()
    np.testing.assert_allclose(n[0], n_rest, atol=1e-12)


def test_a_degenerate_face_without_usable_neighbours_is_named():
    # A stray zero-area triangle of its own three vertices, sharing none with the body.
    v_new = np.array([[0.0, 0.0, 1.0], [0.01, 0.0, 1.0], [0.02, 0.0, 1.0]])
    vertices = np.vstack([BODY.vertices, v_new])
    faces = np.vstack([BODY.faces, len(BODY.vertices) + np.arange(3)[None]])
    body = _with_faces(BODY, vertices, faces, np.r_[BODY.face_segment, 0])
    with pytest.raises(BodyError, match=f"face {len(BODY.faces)} .*zero area.*remove the degenerate faces"):
        body.face_frames()
