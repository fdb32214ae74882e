"""services/common/se2.py, the one twist-limits type, and a guard that no copy of either comes back."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.common.se2 import (
    between,
    compose,
    interpolate,
    interpolate_between,
    inverse,
    quaternion_to_yaw,
    rotate,
    transform_points,
    wrap_angle,
    yaw_to_quaternion,
)

REPO_ROOT = Path(__file__).resolve().parents[1]
angles = st.floats(-100.0, 100.0, allow_nan=False)
coords = st.floats(-50.0, 50.0, allow_nan=False)
poses = st.tuples(coords, coords, angles)


@given(angles)
def test_wrap_angle_range_and_equivalence(a: float) -> None:
    w = wrap_angle(a)
    assert -math.pi < w <= math.pi
    assert math.isclose(math.cos(w), math.cos(a), abs_tol=1e-9) and math.isclose(math.sin(w), math.sin(a),
                                                                                 abs_tol=1e-9)
    arr = wrap_angle(np.array([a]))
    assert -math.pi < arr[0] <= math.pi and arr[0] == pytest.approx(w, abs=1e-9) or abs(abs(w) - math.pi) < 1e-9


def test_wrap_angle_convention_is_minus_pi_exclusive() -> None:
    assert wrap_angle(math.pi) == math.pi and wrap_angle(-math.pi) == math.pi
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    assert wrap_angle(0.3) == 0.3 and wrap_angle(1e-20) == 1e-20  # in range: unchanged, bit for bit
    np.testing.assert_allclose(wrap_angle(np.array([-math.pi, math.pi, 0.1 + 2 * math.pi])), [math.pi, math.pi, 0.1])


@given(poses, poses)
def test_tuple_and_array_forms_agree(a: tuple[float, float, float], b: tuple[float, float, float]) -> None:
    t = compose(a, b)
    arr = compose(np.array(a), np.array(b))
    assert isinstance(t, tuple) and isinstance(arr, np.ndarray)
    assert t[:2] == pytest.approx(tuple(arr[:2]), abs=1e-9)
    assert math.isclose(math.cos(t[2] - arr[2]), 1.0, abs_tol=1e-12)
    assert inverse(a)[:2] == pytest.approx(tuple(inverse(np.array(a))[:2]), abs=1e-9)


@given(poses, poses)
def test_group_laws(a: tuple[float, float, float], b: tuple[float, float, float]) -> None:
    assert compose(a, inverse(a)) == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    back = compose(a, between(a, b))
    assert back[:2] == pytest.approx(b[:2], abs=1e-9) and wrap_angle(back[2] - b[2]) == pytest.approx(0, abs=1e-9)


def test_compose_on_rows_and_points() -> None:
    assert compose((0.0, 0.0, math.pi / 2), (1.0, 0.0, 0.0)) == pytest.approx((0.0, 1.0, math.pi / 2))
    rows = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, math.pi / 2]])
    out = compose(rows, np.broadcast_to([1.0, 0.0, math.pi], rows.shape))
    np.testing.assert_allclose(out, [[1.0, 0.0, math.pi], [1.0, 3.0, -math.pi / 2]], atol=1e-12)
    pts = transform_points((1.0, 2.0, math.pi / 2), np.array([[1.0, 0.0], [0.0, 1.0]]))
    np.testing.assert_allclose(pts, [[1.0, 3.0], [0.0, 2.0]], atol=1e-12)
    mid = interpolate(np.array([0.0, 1.0]), np.array([[0.0, 0.0, 3.0], [2.0, 0.0, -3.0]]), 0.5)
    np.testing.assert_allclose(mid[0, :2], [1.0, 0.0])
    assert abs(wrap_angle(float(mid[0, 2])) - math.pi) < 1e-9  # the shortest arc passes through pi, not 0


def test_rotate_is_the_rotation_of_compose_and_its_inverse_takes_vectors_into_the_frame() -> None:
    theta = 0.7
    x, y = rotate(theta, 1.5, -2.0)
    cx, cy, _ = compose((0.0, 0.0, theta), (1.5, -2.0, 0.0))
    assert (x, y) == pytest.approx((cx, cy), abs=1e-12)
    assert rotate(-theta, x, y) == pytest.approx((1.5, -2.0), abs=1e-12)
    gx, gy = rotate(theta, np.array([[1.0, 0.0], [0.0, 2.0]]), np.zeros((2, 2)))
    np.testing.assert_allclose(gx, [[math.cos(theta), 0.0], [0.0, 2 * math.cos(theta)]], atol=1e-12)
    np.testing.assert_allclose(gy, [[math.sin(theta), 0.0], [0.0, 2 * math.sin(theta)]], atol=1e-12)
    assert quaternion_to_yaw(*yaw_to_quaternion(2.5)) == pytest.approx(2.5, abs=1e-12)
    assert quaternion_to_yaw(*yaw_to_quaternion(-3.0)) == pytest.approx(-3.0, abs=1e-12)


# --------------------------------------------------------------------------- one definition of each


#: 2 pi and pi in the spellings the copies used: ``2 * math.pi``, ``2.0*np.pi``, ``2 * pi``, ``math.tau``, ``TWO_PI``
TWO_PI = r"(2(\.0)?\s*\*\s*((math|np)\.)?pi|((math|np)\.)?tau|TWO_PI|TAU)"
PI = r"((math|np)\.)?pi\b"
COPIES = {
    "angle wrap": [
        r"def (wrap|wrap_angle|normalize_angle|angle_wrap|wrap_to_pi)\((?!self)",
        r"(atan2|arctan2)\(\s*((math|np)\.)?sin\(",
        rf"%\s*\(?\s*{TWO_PI}\s*\)?\s*-\s*{PI}",
        rf"(np\.)?mod\([^;]*,\s*{TWO_PI}\s*\)\s*-\s*{PI}",
        rf"remainder\([^)]*,\s*{TWO_PI}\s*\)",
        rf"[-+]=\s*{TWO_PI}\b",
        r"angle\(\s*np\.exp\(\s*1j",
    ],
    "SE(2) compose": [
        r"def (_?compose|_?inverse|relative|_?between|oplus|ominus)\(",
        r"\+ (c|ct|math\.cos\([^)]*\)) \* \w+(\[0\]|\.x) - (s|st|math\.sin\([^)]*\)) \* \w+(\[1\]|\.y)",
    ],
    "quaternion and yaw": [
        r"def _?(yaw_to_quat|quat_to_yaw|quaternion_from_yaw|yaw_from_quat|quaternion_to_yaw|yaw_to_quaternion)\w*\(",
        r"atan2\(\s*2(\.0)?\s*\*\s*\(\s*[\w.]*w\s*\*\s*[\w.]*z",
        r"\bsin\(\s*[\w.]+\s*/\s*2(\.0)?\s*\),\s*\w*\s*=?\s*(math\.)?cos\(",
    ],
    "twist limits": [
        r"def clamp_twist\(",
        r"class (Twist)?Limits\b",
    ],
}
HOME = {"services/common/se2.py", "services/common/robot.py"}


def test_one_definition_of_wrap_compose_and_twist_limits() -> None:
    """Every angle wrap, SE(2) composition, quaternion/yaw conversion and twist clamp goes through services/common
    (se2.py, robot.py)."""
    copies = []
    for folder in ("services", "proto", "tools", "tests"):
        for path in sorted((REPO_ROOT / folder).rglob("*.py")):
            rel = path.relative_to(REPO_ROOT).as_posix()
            if rel in HOME or rel == "tests/test_se2.py":
                continue
            text = path.read_text(encoding="utf-8")
            for helper, patterns in COPIES.items():
                for pattern in patterns:
                    for match in re.finditer(pattern, text):
                        line = text.count("\n", 0, match.start()) + 1
                        copies.append(f"{rel}:{line}: {helper}: {match.group(0)!r}")
    assert not copies, "use services/common/se2.py or TwistLimits instead of a copy:\n" + "\n".join(copies)


def test_the_guard_sees_a_copy(tmp_path: Path) -> None:
    """The patterns above match the forms the copies had and other spellings of them (so the guard can fail), and
    not the one-sided folds that are not a wrap."""
    forms = {
        "angle wrap": ["def wrap(a):", "math.atan2(math.sin(t), math.cos(t))",
                       "(a + math.pi) % (2 * math.pi) - math.pi", "math.remainder(b - a, 2 * math.pi)",
                       "(t + math.pi) % TWO_PI - math.pi", "(a + pi) % (2 * pi) - pi",
                       "np.arctan2(np.sin(th), np.cos(th))", "atan2(sin(a), cos(a))",
                       "np.mod(d + np.pi, 2.0*np.pi) - np.pi", "(a + math.pi) % math.tau - math.pi",
                       "a -= 2 * math.pi", "th += 2.0 * np.pi", "np.angle(np.exp(1j * a))"],
        "SE(2) compose": ["def compose(a, b):", "a[0] + c * b[0] - s * b[1]", "r.x + c * mx.x - s * my.y"],
        "quaternion and yaw": ["def yaw_to_quat(theta):", "def quat_to_yaw(x, y, z, w):",
                               "math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))",
                               "math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y ** 2 + q.z ** 2))",
                               "z=math.sin(theta / 2.0), w=math.cos(theta / 2.0)"],
        "twist limits": ["def clamp_twist(self):", "class Limits:"],
    }
    for helper, samples in forms.items():
        for sample in samples:
            assert any(re.search(p, sample) for p in COPIES[helper]), (helper, sample)
    not_copies = ["np.mod(wrap_angle(b - a), 2 * math.pi)", "roll = math.atan2(2 * (q.w * q.x + q.y * q.z), 1)"]
    for sample in not_copies:
        assert not any(re.search(p, sample) for patterns in COPIES.values() for p in patterns), sample


def test_robot_pose_and_frame_prefers_map_odom_then_odometry_then_the_map_pose() -> None:
    from services.common.se2 import robot_pose_and_frame

    odom, map_odom, map_pose = (1.0, 0.0, 0.0), (0.0, 2.0, math.pi / 2), (5.0, 5.0, 0.0)
    pose, frame = robot_pose_and_frame(odom, map_odom, map_pose) or ((0.0, 0.0, 0.0), "")
    assert frame == "map" and pose == pytest.approx((0.0, 3.0, math.pi / 2))
    assert robot_pose_and_frame(odom, None, None) == (odom, "odom")
    assert robot_pose_and_frame(odom, None, map_pose) == (map_pose, "map")
    assert robot_pose_and_frame(None, map_odom, map_pose) == (map_pose, "map")
    assert robot_pose_and_frame(None, None, None) is None


def test_interpolate_between_two_poses_matches_the_array_interpolation():
    rng = np.random.default_rng(7)
    for _ in range(200):
        a = (*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi))
        b = (a[0] + rng.uniform(-1, 1), a[1] + rng.uniform(-1, 1), rng.uniform(-np.pi, np.pi))
        f = rng.uniform(0, 1)
        expected = interpolate(np.array([0.0, 1.0]), np.array([a, b]), f)[0]
        got = interpolate_between(a, b, f)
        assert np.allclose(got[:2], expected[:2], atol=1e-12)
        assert abs(np.angle(np.exp(1j * (got[2] - expected[2])))) < 1e-12
