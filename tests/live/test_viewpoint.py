"""Virtual viewpoints of rig.live.viewpoint on the simulator's six-camera arc rig (left, sup1 ..
sup4, right, 60 degrees apart, all aimed at the same point): the arc ends are the sources, the arc
looks at the subject, the orbit and zoom stay in their bounds, and any message a browser can send
is either a Viewpoint or a ValueError."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.camera import CameraModel, RigCalibration, look_at
from inference.runtime.preprocess import pinhole
from rig.live.viewpoint import (
    PITCH_LIMIT_DEG,
    YAW_MARGIN_DEG,
    ZOOM_RANGE,
    Viewpoint,
    arc_camera,
    matrix_from_quat,
    parse_viewpoint,
    presets,
    quat_from_matrix,
    slerp,
    source_arc,
    subject_point,
)
from simulator.rig import virtual_rig

RIG = virtual_rig(6, 640, 360)
LEFT, RIGHT = RIG["left"], RIG["right"]
SUBJECT = np.array([0.0, 1.0, 0.0])  # where simulator.rig aims every camera


def assert_same_camera(a: CameraModel, b: CameraModel, atol: float = 1e-9) -> None:
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_allclose(a.K, b.K, atol=atol)
    np.testing.assert_allclose(a.R, b.R, atol=atol)
    np.testing.assert_allclose(a.t, b.t, atol=atol)
    assert not a.has_distortion


def off_axis(camera: CameraModel, point: np.ndarray) -> float:
    """Distance of a point from the camera's optical axis (0: the camera looks straight at it)."""
    v = point - camera.center
    d = camera.R[2]
    assert np.dot(v, d) > 0, "the point is behind the camera"
    return float(np.linalg.norm(v - np.dot(v, d) * d))


def test_the_rig_is_the_six_camera_arc():
    assert RIG.names == ["left", "sup1", "sup2", "sup3", "sup4", "right"]


# -- the arc ----------------------------------------------------------------------------------------
def test_arc_ends_are_the_source_pinholes():
    assert_same_camera(arc_camera(LEFT, RIGHT, 0.0), pinhole(LEFT, (640, 360)))
    assert_same_camera(arc_camera(LEFT, RIGHT, 1.0), pinhole(RIGHT, (640, 360)))
    # at another size too (the intrinsics follow CameraModel.scaled)
    assert_same_camera(arc_camera(LEFT, RIGHT, 0.0, (320, 180)), pinhole(LEFT, (320, 180)))
    assert_same_camera(arc_camera(LEFT, RIGHT, 1.0, (1280, 720)), pinhole(RIGHT, (1280, 720)))
    # and the ends are approached continuously
    assert_same_camera(arc_camera(LEFT, RIGHT, 1e-9), pinhole(LEFT, (640, 360)), atol=1e-6)
    assert_same_camera(arc_camera(LEFT, RIGHT, 1 - 1e-9), pinhole(RIGHT, (640, 360)), atol=1e-6)


def test_subject_is_where_the_source_axes_meet():
    p, found = subject_point(LEFT, RIGHT)
    assert found
    np.testing.assert_allclose(p, SUBJECT, atol=1e-9)


def test_halfway_is_between_the_sources_and_looks_at_the_subject():
    mid = arc_camera(LEFT, RIGHT, 0.5)
    c, cl, cr = mid.center, LEFT.center, RIGHT.center
    # equidistant from both sources, on the rig's circle (radius 3.6 about the vertical through the subject)
    assert np.linalg.norm(c - cl) == pytest.approx(np.linalg.norm(c - cr), rel=1e-9)
    assert np.linalg.norm(c - cl) < np.linalg.norm(cr - cl)
    np.testing.assert_allclose(c, [0.0, 1.5, 3.6], atol=1e-9)
    assert off_axis(mid, SUBJECT) < 1e-9
    # the subject projects to the principal point
    uv, z = mid.project(SUBJECT)
    np.testing.assert_allclose(uv, [mid.cx, mid.cy], atol=1e-6)
    assert z > 0
    # intrinsics: the mean of the two sources'
    np.testing.assert_allclose(mid.K, (LEFT.K + RIGHT.K) / 2, atol=1e-9)


@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_arc_passes_through_the_supervision_cameras_poses(k):
    """The simulator's supervision cameras stand on the same circle, 12 degrees apart: the arc at
    t = k/5 has sup_k's pose (its lens differs)."""
    virtual = arc_camera(LEFT, RIGHT, k / 5)
    sup = RIG[f"sup{k}"]
    np.testing.assert_allclose(virtual.R, sup.R, atol=1e-9)
    np.testing.assert_allclose(virtual.center, sup.center, atol=1e-9)


def test_every_arc_camera_looks_at_the_subject_and_moves_monotonically():
    arc = source_arc(LEFT, RIGHT)
    assert arc.span_deg == pytest.approx(60.0, abs=1e-9)
    az = []
    for t in np.linspace(0, 1, 21):
        cam = arc_camera(LEFT, RIGHT, float(t))
        assert off_axis(cam, SUBJECT) < 1e-9
        assert np.allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12) and np.linalg.det(cam.R) == pytest.approx(1.0)
        az.append(arc.azimuth_deg(cam.center))
    np.testing.assert_allclose(az, np.linspace(0, 60, 21), atol=1e-9)


def test_parallel_sources_interpolate_the_centre_linearly():
    R, t = look_at([-0.5, 1.5, 3.0], [-0.5, 1.5, 0.0])
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 179.5], [0, 0, 1]])
    a = CameraModel("left", 640, 360, K, np.zeros(5), R, t)
    b = a.with_pose(R, -R @ np.array([0.5, 1.5, 3.0]))
    p, found = subject_point(a, b)
    assert not found
    np.testing.assert_allclose(p, [0.0, 1.5, 2.0], atol=1e-9)  # the baseline (1 m) ahead of its middle
    for t in (0.25, 0.5, 0.8):
        cam = arc_camera(a, b, t)
        np.testing.assert_allclose(cam.center, (1 - t) * a.center + t * b.center, atol=1e-9)
        np.testing.assert_allclose(cam.R, R, atol=1e-9)
    # diverging axes: no subject in front of both either
    Ra, ta = look_at([-0.5, 1.5, 3.0], [-5.0, 1.5, 0.0])
    Rb, tb = look_at([0.5, 1.5, 3.0], [5.0, 1.5, 0.0])
    assert not subject_point(a.with_pose(Ra, ta), a.with_pose(Rb, tb))[1]


def test_arc_refuses_t_outside_zero_to_one():
    for bad in (-0.1, 1.5, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            arc_camera(LEFT, RIGHT, bad)


# -- slerp ------------------------------------------------------------------------------------------
def _angle(q0, q1) -> float:
    # 2 atan2(|q0 - q1|, |q0 + q1|) (q1 on q0's side): exact near 0, where acos(dot) loses half the
    # digits (a dot product rounded to 1 - 1e-16 reads as 3e-8 rad, and how it rounds varies by CPU).
    q1 = q1 if float(np.dot(q0, q1)) >= 0 else -q1
    return 2 * math.atan2(float(np.linalg.norm(q0 - q1)), float(np.linalg.norm(q0 + q1)))


@pytest.mark.parametrize("seed", range(5))
def test_slerp_is_unit_norm_and_monotone(seed):
    rng = np.random.default_rng(seed)
    q0, q1 = (q / np.linalg.norm(q) for q in rng.normal(size=(2, 4)))
    total = _angle(q0, q1)
    ts = np.linspace(0, 1, 41)
    qs = [slerp(q0, q1, float(t)) for t in ts]
    assert all(abs(np.linalg.norm(q) - 1) < 1e-12 for q in qs)
    angles = [_angle(q0, q) for q in qs]
    assert all(b > a for a, b in zip(angles, angles[1:]))
    np.testing.assert_allclose(angles, ts * total, atol=1e-9)  # constant angular speed
    assert _angle(qs[-1], q1) < 1e-9


def test_slerp_takes_the_shorter_way_and_quaternions_round_trip():
    R = look_at([1.0, 2.0, 3.0], [0.0, 1.0, 0.0])[0]
    q = quat_from_matrix(R)
    np.testing.assert_allclose(matrix_from_quat(q), R, atol=1e-12)
    # -q is the same rotation: halfway between q and -q is q itself, not a half turn
    np.testing.assert_allclose(matrix_from_quat(slerp(q, -q, 0.5)), R, atol=1e-12)
    for R in (np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])):  # trace -1
        np.testing.assert_allclose(matrix_from_quat(quat_from_matrix(R)), R, atol=1e-12)


# -- presets ------------------------------------------------------------------------------------------
def test_presets_are_every_calibrated_camera():
    # t: where each stands along the arc between the sources (the slider's reading once it is chosen)
    assert presets(RIG) == [{"name": "left", "kind": "source", "t": 0.0}, {"name": "sup1", "kind": "supervision", "t": 0.2},
                            {"name": "sup2", "kind": "supervision", "t": 0.4}, {"name": "sup3", "kind": "supervision", "t": 0.6},
                            {"name": "sup4", "kind": "supervision", "t": 0.8}, {"name": "right", "kind": "source", "t": 1.0}]
    for name in RIG.names:
        vp = parse_viewpoint({"type": "viewpoint", "preset": name}, RIG)
        assert vp.preset == name
        assert_same_camera(vp.camera(RIG), pinhole(RIG[name], (640, 360)))
        assert_same_camera(vp.camera(RIG, (320, 180)), pinhole(RIG[name], (320, 180)))


def test_sources_may_have_other_names():
    cams = [CameraModel({"left": "cam-a", "right": "cam-b"}.get(c.name, c.name), c.width, c.height, c.K, c.dist, c.R, c.t)
            for c in RIG.cameras]
    rig = RigCalibration(cams)
    with pytest.raises(ValueError, match="no source camera"):
        parse_viewpoint({"type": "viewpoint", "t": 0.5}, rig)
    vp = parse_viewpoint({"type": "viewpoint", "t": 0.5}, rig, sources=("cam-a", "cam-b"))
    assert_same_camera(vp.camera(rig, sources=("cam-a", "cam-b")), arc_camera(LEFT, RIGHT, 0.5))
    assert presets(rig, ("cam-a", "cam-b"))[0] == {"name": "cam-a", "kind": "source", "t": 0.0}
    assert [p["t"] for p in presets(rig)] == [None] * 6  # no arc without the sources


# -- messages -----------------------------------------------------------------------------------------
def test_messages_of_the_live_issue():
    vp = parse_viewpoint({"type": "viewpoint", "t": 0.3}, RIG)
    assert vp == Viewpoint(t=0.3)
    assert_same_camera(vp.camera(RIG), arc_camera(LEFT, RIGHT, 0.3))
    assert parse_viewpoint({"type": "viewpoint", "preset": "sup2"}, RIG) == Viewpoint(t=None, preset="sup2")
    vp = parse_viewpoint({"type": "viewpoint", "t": 0.5, "yaw": 10, "pitch": -5, "zoom": 1.5}, RIG)
    assert (vp.t, vp.yaw, vp.pitch, vp.zoom) == (0.5, 10.0, -5.0, 1.5)
    cam = vp.camera(RIG, (320, 180))
    assert (cam.width, cam.height) == (320, 180)
    assert off_axis(cam, SUBJECT) < 1e-9  # an orbit about the subject keeps looking at it
    mid = arc_camera(LEFT, RIGHT, 0.5, (320, 180))
    np.testing.assert_allclose(cam.K[:2, :2], 1.5 * mid.K[:2, :2])
    np.testing.assert_allclose(cam.K[:2, 2], mid.K[:2, 2])
    assert np.linalg.norm(cam.center - SUBJECT) == pytest.approx(np.linalg.norm(mid.center - SUBJECT))
    assert cam.center[1] < mid.center[1]  # pitch -5: lower
    assert parse_viewpoint({"type": "viewpoint"}, RIG) == Viewpoint(t=0.5)


def test_yaw_turns_along_the_arc_and_pitch_up_looks_down():
    turned, along = parse_viewpoint({"type": "viewpoint", "t": 0.25, "yaw": 15}, RIG).camera(RIG), arc_camera(LEFT, RIGHT, 0.5)
    np.testing.assert_allclose(turned.R, along.R, atol=1e-9)  # the pose of t = 0.5 (the lens stays t = 0.25's)
    np.testing.assert_allclose(turned.t, along.t, atol=1e-9)
    up = parse_viewpoint({"type": "viewpoint", "t": 0.5, "pitch": 10}, RIG).camera(RIG)
    mid = arc_camera(LEFT, RIGHT, 0.5)
    assert up.center[1] > mid.center[1]
    assert off_axis(up, SUBJECT) < 1e-9
    elevation = lambda c: math.degrees(math.asin((c.center - SUBJECT)[1] / np.linalg.norm(c.center - SUBJECT)))
    assert elevation(up) - elevation(mid) == pytest.approx(10.0, abs=1e-9)


def test_orbit_and_zoom_are_clamped_to_their_bounds():
    def vp(**fields):
        return parse_viewpoint({"type": "viewpoint", **fields}, RIG)

    assert vp(t=0.0, yaw=-40).yaw == pytest.approx(-YAW_MARGIN_DEG)
    assert vp(t=1.0, yaw=40).yaw == pytest.approx(YAW_MARGIN_DEG)
    assert vp(t=0.5, yaw=-180).yaw == pytest.approx(-30 - YAW_MARGIN_DEG)
    assert vp(t=0.5, yaw=44).yaw == 44.0
    assert vp(preset="sup2", yaw=90).yaw == pytest.approx(60 + YAW_MARGIN_DEG - 24)
    assert vp(preset="right", yaw=1).yaw == pytest.approx(1.0)
    assert vp(t=0.5, pitch=45).pitch == PITCH_LIMIT_DEG
    assert vp(t=0.5, pitch=-90).pitch == -PITCH_LIMIT_DEG
    assert vp(t=0.5, zoom=10).zoom == ZOOM_RANGE[1]
    assert vp(t=0.5, zoom=0.1).zoom == ZOOM_RANGE[0]
    # a camera outside the bounds (here: 150 degrees round from the left source) may stay or turn
    # towards the arc, never further out
    a = math.radians(120)
    R, t = look_at([3.6 * math.sin(a), 1.5, 3.6 * math.cos(a)], SUBJECT)
    sup2 = RIG["sup2"]
    rig = RigCalibration(RIG.cameras + [CameraModel("back", sup2.width, sup2.height, sup2.K, sup2.dist, R, t)])
    assert parse_viewpoint({"type": "viewpoint", "preset": "back"}, rig).yaw == 0.0
    assert source_arc(LEFT, RIGHT).azimuth_deg(rig["back"].center) == pytest.approx(150)
    assert parse_viewpoint({"type": "viewpoint", "preset": "back", "yaw": 20}, rig).yaw == 0.0  # 150 -> 170: further out
    assert parse_viewpoint({"type": "viewpoint", "preset": "back", "yaw": -20}, rig).yaw == -20.0  # towards the arc
    arc = source_arc(LEFT, RIGHT)
    for yaw in (-180, -90, 90, 180):
        cam = vp(t=0.7, yaw=yaw).camera(RIG)
        assert -YAW_MARGIN_DEG - 1e-9 <= arc.azimuth_deg(cam.center) <= 60 + YAW_MARGIN_DEG + 1e-9


def test_viewpoints_are_hashable_and_round_trip_through_json():
    a = parse_viewpoint({"type": "viewpoint", "t": 0.5, "yaw": 10}, RIG)
    b = parse_viewpoint({"type": "viewpoint", "t": 0.5, "yaw": 10.0}, RIG)
    assert a == b and hash(a) == hash(b) and len({a, b, Viewpoint(t=0.6)}) == 2
    cache = {a: "rendered"}
    assert cache[b] == "rendered"
    for msg in ({"type": "viewpoint", "t": 0.3}, {"type": "viewpoint", "preset": "sup3", "zoom": 2},
                {"type": "viewpoint", "t": 1, "yaw": 90, "pitch": -30, "zoom": 0.2}):
        v = parse_viewpoint(msg, RIG)
        again = parse_viewpoint(json.loads(json.dumps(v.to_message())), RIG)
        assert again == v


BAD_MESSAGES = [
    ("not a dict", "JSON object"),
    (None, "JSON object"),
    ([{"type": "viewpoint"}], "JSON object"),
    ({}, "type"),
    ({"type": "ack", "t": 0.5}, "type"),
    ({"type": "viewpoint", "t": float("nan")}, "finite"),
    ({"type": "viewpoint", "t": float("inf")}, "finite"),
    ({"type": "viewpoint", "t": -float("inf")}, "finite"),
    ({"type": "viewpoint", "t": 1e300}, "between 0 and 1"),
    ({"type": "viewpoint", "t": -0.01}, "between 0 and 1"),
    ({"type": "viewpoint", "t": 1.01}, "between 0 and 1"),
    ({"type": "viewpoint", "t": 10**400}, "between 0 and 1"),
    ({"type": "viewpoint", "t": "0.3"}, "number"),
    ({"type": "viewpoint", "t": True}, "number"),
    ({"type": "viewpoint", "t": None}, "number"),
    ({"type": "viewpoint", "t": [0.3]}, "number"),
    ({"type": "viewpoint", "t": {"value": 0.3}}, "number"),
    ({"type": "viewpoint", "preset": "sup9"}, "unknown preset"),
    ({"type": "viewpoint", "preset": ""}, "unknown preset"),
    ({"type": "viewpoint", "preset": "x" * 100000}, "unknown preset"),
    ({"type": "viewpoint", "preset": 2}, "camera name"),
    ({"type": "viewpoint", "preset": ["sup2"]}, "camera name"),
    ({"type": "viewpoint", "preset": "sup2", "t": 0.5}, "not both"),
    ({"type": "viewpoint", "t": 0.5, "fov": 60}, "unknown viewpoint field"),
    ({"type": "viewpoint", "t": 0.5, "__proto__": {}}, "unknown viewpoint field"),
    ({"type": "viewpoint", "t": 0.5, 3: 1}, "unknown viewpoint field"),
    ({"type": "viewpoint", "yaw": float("nan")}, "finite"),
    ({"type": "viewpoint", "yaw": 1e9}, "yaw must be between"),
    ({"type": "viewpoint", "yaw": "left"}, "number"),
    ({"type": "viewpoint", "pitch": -1e308}, "pitch must be between"),
    ({"type": "viewpoint", "pitch": False}, "number"),
    ({"type": "viewpoint", "zoom": 0}, "zoom must be between"),
    ({"type": "viewpoint", "zoom": -1.5}, "zoom must be between"),
    ({"type": "viewpoint", "zoom": float("inf")}, "finite"),
    ({"type": "viewpoint", "zoom": 1e6}, "zoom must be between"),
]


@pytest.mark.parametrize("message,reason", BAD_MESSAGES, ids=[str(i) for i in range(len(BAD_MESSAGES))])
def test_bad_messages_raise_value_error_with_a_one_line_reason(message, reason):
    with pytest.raises(ValueError) as info:
        parse_viewpoint(message, RIG)
    text = str(info.value)
    assert reason in text and "\n" not in text and len(text) < 300


JSON_SCALARS = st.one_of(st.none(), st.booleans(), st.integers(min_value=-(10**400), max_value=10**400),
                         st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=20),
                         st.sampled_from(RIG.names + ["sup0", "LEFT", " left"]))
JSON_VALUES = st.recursive(JSON_SCALARS, lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
                           max_leaves=6)
KEYS = st.sampled_from(["type", "t", "preset", "yaw", "pitch", "zoom"]) | st.text(max_size=8)
MESSAGES = st.one_of(
    st.dictionaries(KEYS, JSON_VALUES, max_size=6),
    st.fixed_dictionaries({"type": st.just("viewpoint")},
                          optional={"t": JSON_SCALARS, "preset": JSON_SCALARS, "yaw": JSON_SCALARS,
                                    "pitch": JSON_SCALARS, "zoom": JSON_SCALARS}),
    st.fixed_dictionaries({"type": st.just("viewpoint")},
                          optional={"t": st.floats(-0.5, 1.5), "yaw": st.floats(-400, 400), "pitch": st.floats(-200, 200),
                                    "zoom": st.floats(-1, 50)}),
    JSON_VALUES,
)


@settings(max_examples=400, deadline=None)
@given(MESSAGES)
def test_any_message_is_a_viewpoint_or_a_value_error(message):
    try:
        vp = parse_viewpoint(message, RIG)
    except ValueError as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    assert isinstance(vp, Viewpoint)
    hash(vp)
    assert -PITCH_LIMIT_DEG <= vp.pitch <= PITCH_LIMIT_DEG and ZOOM_RANGE[0] <= vp.zoom <= ZOOM_RANGE[1]
    cam = vp.camera(RIG, (64, 36))
    assert np.all(np.isfinite(cam.K)) and np.all(np.isfinite(cam.R)) and np.all(np.isfinite(cam.t))
    assert off_axis(cam, SUBJECT) < 1e-6 if vp.preset is None else True
    az = source_arc(LEFT, RIGHT).azimuth_deg(cam.center)
    assert -YAW_MARGIN_DEG - 1e-6 <= az <= 60 + YAW_MARGIN_DEG + 1e-6
    assert parse_viewpoint(vp.to_message(), RIG) == vp
