"""The ROS 2 example node's message conversions, without ROS: stand-ins with the messages' fields."""

from __future__ import annotations

import importlib.util
import sys
from dataclasses import dataclass, field

import numpy as np
import pytest

from checkout import ROOT


def _load_node_module():
    spec = importlib.util.spec_from_file_location("ros2_node_example", ROOT / "examples" / "ros2_node.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


ros = _load_node_module()


@dataclass
class Image:  # sensor_msgs/Image
    height: int = 0
    width: int = 0
    encoding: str = ""
    is_bigendian: int = 0
    step: int = 0
    data: bytes = b""


@dataclass
class CameraInfo:  # sensor_msgs/CameraInfo
    width: int = 0
    height: int = 0
    k: list[float] = field(default_factory=lambda: [0.0] * 9)


@dataclass
class Point:
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


@dataclass
class Quaternion:
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    w: float = 1.0


@dataclass
class Pose:  # geometry_msgs/Pose
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class JointState:  # sensor_msgs/JointState
    name: list[str] = field(default_factory=list)
    position: list[float] = field(default_factory=list)


def test_importing_the_node_does_not_import_ros() -> None:
    assert "rclpy" not in sys.modules and callable(ros.main)


def test_rgb8_and_bgr8_with_row_padding() -> None:
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    padded = np.zeros((2, 12), np.uint8)  # step 12 > 9 bytes per row
    padded[:, :9] = rgb.reshape(2, 9)
    msg = Image(height=2, width=3, encoding="rgb8", step=12, data=padded.tobytes())
    assert np.array_equal(ros.image_to_array(msg), rgb)
    bgr = Image(height=2, width=3, encoding="bgr8", step=9, data=rgb[..., ::-1].tobytes())
    assert np.array_equal(ros.image_to_array(bgr), rgb)


def test_16uc1_depth_in_millimetres_both_byte_orders() -> None:
    mm = np.array([[0, 380], [1000, 65535]], dtype=np.uint16)
    little = Image(height=2, width=2, encoding="16UC1", step=4, data=mm.astype("<u2").tobytes())
    big = Image(height=2, width=2, encoding="16UC1", is_bigendian=1, step=4, data=mm.astype(">u2").tobytes())
    for msg in (little, big):
        assert np.allclose(ros.depth_to_metres(msg), [[0, 0.38], [1.0, 65.535]])


def test_32fc1_depth_non_finite_is_no_return() -> None:
    metres = np.array([[np.nan, 0.5], [np.inf, -1.0]], dtype=np.float32)
    msg = Image(height=2, width=2, encoding="32FC1", step=8, data=metres.tobytes())
    depth = ros.depth_to_metres(msg)
    assert depth.dtype == np.float32 and depth.tolist() == [[0, 0.5], [0, 0]]


def test_mono8_mask() -> None:
    msg = Image(height=1, width=3, encoding="mono8", step=3, data=bytes([0, 255, 1]))
    assert ros.mask_to_array(msg).tolist() == [[False, True, True]]
    with pytest.raises(ValueError, match="mono8"):
        ros.mask_to_array(Image(height=1, width=1, encoding="rgb8", step=3, data=b"abc"))


@pytest.mark.parametrize(
    ("encoding", "array"),
    [
        ("rgb8", np.arange(12, dtype=np.uint8).reshape(2, 2, 3)),
        ("bgr8", np.arange(12, dtype=np.uint8).reshape(2, 2, 3)),
        ("mono8", np.array([[0, 255]], np.uint8)),
        ("16UC1", np.array([[0, 65535], [380, 1]], np.uint16)),
        ("32FC1", np.array([[0.5, 1e-9]], np.float32)),
    ],
)
def test_array_to_image_round_trip(encoding: str, array: np.ndarray) -> None:
    msg = ros.array_to_image(array, encoding, Image())
    assert (msg.height, msg.width, msg.encoding) == (*array.shape[:2], encoding)
    assert msg.step * msg.height == len(msg.data)
    assert np.array_equal(ros.image_to_array(msg), array)


def test_bad_images_raise_naming_the_problem() -> None:
    with pytest.raises(ValueError, match="unsupported image encoding 'yuv422'"):
        ros.image_to_array(Image(height=1, width=1, encoding="yuv422", step=2, data=b"ab"))
    with pytest.raises(ValueError, match="step"):
        ros.image_to_array(Image(height=1, width=2, encoding="rgb8", step=3, data=b"abcdef"))
    with pytest.raises(ValueError, match="holds 3 bytes"):
        ros.image_to_array(Image(height=2, width=1, encoding="rgb8", step=3, data=b"abc"))
    with pytest.raises(ValueError, match="16UC1"):
        ros.depth_to_metres(Image(height=1, width=1, encoding="mono8", step=1, data=b"a"))
    with pytest.raises(ValueError, match="uint16"):
        ros.array_to_image(np.zeros((2, 2), np.float32), "16UC1", Image())


def test_camera_info_to_k() -> None:
    info = CameraInfo(width=640, height=480, k=[536.5, 0, 319.5, 0, 536.5, 239.5, 0, 0, 1])
    K, width, height = ros.camera_info_to_k(info)
    assert K.shape == (3, 3) and K[0, 2] == 319.5 and (width, height) == (640, 480)
    with pytest.raises(ValueError, match="calibrated"):
        ros.camera_info_to_k(CameraInfo(width=640, height=480))


def test_pose_round_trip_at_half_turn() -> None:
    msg = Pose(Point(0.1, -0.2, 0.5), Quaternion(0.0, 0.0, 1.0, 0.0))  # 180 degrees about z
    pose = ros.pose_from_msg(msg)
    assert np.allclose(pose.matrix[:3, :3], np.diag([-1, -1, 1]), atol=1e-12)
    back = ros.pose_to_msg(pose, Pose())
    assert (back.position.x, back.position.y, back.position.z) == pytest.approx((0.1, -0.2, 0.5))
    assert (back.orientation.z, back.orientation.w) == pytest.approx((1.0, 0.0))
    assert isinstance(back.orientation.w, float)


def test_joint_state_round_trip() -> None:
    joints = {"jaw_slide": 0.01, "jaw_turn": -0.25}
    msg = ros.joints_to_msg(joints, JointState())
    assert msg.name == ["jaw_slide", "jaw_turn"] and ros.joints_from_msg(msg) == joints
    with pytest.raises(ValueError, match="2 names but 1 positions"):
        ros.joints_from_msg(JointState(name=["a", "b"], position=[0.0]))
