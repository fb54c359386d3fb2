"""A ROS 2 node that tracks an articulated object's pose and joints through the NARF service.

    ros2 run ... / python examples/ros2_node.py --ros-args -p server_url:=http://narf:8000 -p model:=clamp

Subscribes (remap as needed):
  image         sensor_msgs/Image, rgb8 or bgr8
  depth         sensor_msgs/Image, 16UC1 millimetres or 32FC1 metres, registered to ``image``
                (parameter ``use_depth``, default true; false: RGB only)
  mask          sensor_msgs/Image, mono8 (non-zero = object), stamped like ``image``
  camera_info   sensor_msgs/CameraInfo (``k``, images undistorted upstream)
  initial_pose  geometry_msgs/PoseStamped: where to start (re)tracking, in the camera frame
Publishes:
  ~/pose          geometry_msgs/PoseWithCovarianceStamped, ``T_cam_obj`` in the image's frame with the
                  tracker's covariance, the image's stamp (nothing while the track is lost)
  ~/joint_states  sensor_msgs/JointState
Frames go to ``POST /v1/track`` with the image's stamp as their time; the node keeps only the
server's state token, so any replica behind ``server_url`` can answer. Frames arriving while one
is in flight are dropped.

ROS is imported only in :func:`main`. Everything else here is a pure conversion between ROS message
fields and numpy / narf_client types, tested without ROS (tests/test_ros_conversions.py).
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from typing import Any

import numpy as np
from narf_client import Pose

_CHANNELS = {  # encoding -> (channels, dtype)
    "rgb8": (3, np.uint8),
    "bgr8": (3, np.uint8),
    "mono8": (1, np.uint8),
    "8UC1": (1, np.uint8),
    "16UC1": (1, np.uint16),
    "mono16": (1, np.uint16),
    "32FC1": (1, np.float32),
}


def image_to_array(msg: Any) -> np.ndarray:
    """``sensor_msgs/Image`` -> array: ``[H, W, 3]`` uint8 for rgb8/bgr8 (always returned as RGB),
    ``[H, W]`` uint8, uint16 or float32 for mono8/8UC1, 16UC1/mono16, 32FC1. Honours ``step`` (row
    padding) and ``is_bigendian``."""
    if msg.encoding not in _CHANNELS:
        raise ValueError(f"unsupported image encoding {msg.encoding!r}; expected one of {', '.join(_CHANNELS)}")
    channels, dtype = _CHANNELS[msg.encoding]
    dtype = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    row_bytes = msg.width * channels * dtype.itemsize
    if msg.step < row_bytes:
        raise ValueError(f"image step {msg.step} is shorter than a row ({row_bytes} bytes)")
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if data.size < msg.step * msg.height:
        raise ValueError(f"image data holds {data.size} bytes, expected {msg.step * msg.height}")
    rows = data[: msg.step * msg.height].reshape(msg.height, msg.step)[:, :row_bytes]
    array = np.ascontiguousarray(rows).view(dtype).astype(dtype.newbyteorder("="))
    array = array.reshape(msg.height, msg.width, channels) if channels > 1 else array.reshape(msg.height, msg.width)
    return array[..., ::-1].copy() if msg.encoding == "bgr8" else array


def depth_to_metres(msg: Any) -> np.ndarray:
    """A depth image (16UC1 millimetres or 32FC1 metres) -> float32 metres ``[H, W]``, 0 = no return."""
    if msg.encoding in ("16UC1", "mono16"):
        return image_to_array(msg).astype(np.float32) / 1000
    if msg.encoding == "32FC1":
        depth = image_to_array(msg)
        return np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
    raise ValueError(f"a depth image must be 16UC1 (mm) or 32FC1 (m), got {msg.encoding!r}")


def mask_to_array(msg: Any) -> np.ndarray:
    """A mono8 / 8UC1 mask image -> bool ``[H, W]`` (non-zero = object)."""
    if msg.encoding not in ("mono8", "8UC1"):
        raise ValueError(f"a mask must be mono8 or 8UC1, got {msg.encoding!r}")
    return image_to_array(msg) != 0


def array_to_image(array: np.ndarray, encoding: str, msg: Any) -> Any:
    """Fill ``msg`` (a ``sensor_msgs/Image``) with ``array`` in ``encoding``; returns ``msg``."""
    if encoding not in _CHANNELS:
        raise ValueError(f"unsupported image encoding {encoding!r}")
    channels, dtype = _CHANNELS[encoding]
    array = np.asarray(array)
    shape_ok = array.ndim == 2 if channels == 1 else (array.ndim == 3 and array.shape[2] == channels)
    if array.dtype != dtype or not shape_ok:
        raise ValueError(f"{encoding} needs {np.dtype(dtype)} with {channels} channel(s), got {array.dtype} {array.shape}")
    if encoding == "bgr8":
        array = array[..., ::-1]
    array = np.ascontiguousarray(array, dtype=np.dtype(dtype).newbyteorder("<"))
    msg.height, msg.width = array.shape[:2]
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = array.shape[1] * channels * array.itemsize
    msg.data = array.tobytes()
    return msg


def camera_info_to_k(msg: Any) -> tuple[np.ndarray, int, int]:
    """``sensor_msgs/CameraInfo`` -> ``(K [3, 3], width, height)``; an uncalibrated (all-zero) ``k`` is refused."""
    K = np.asarray(msg.k, dtype=np.float64)
    if K.shape != (9,):
        raise ValueError(f"CameraInfo.k must hold 9 values, got {K.size}")
    K = K.reshape(3, 3)
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError("CameraInfo.k has no positive focal length: is the camera calibrated?")
    return K, int(msg.width), int(msg.height)


def pose_from_msg(msg: Any) -> Pose:
    """``geometry_msgs/Pose`` -> :class:`narf_client.Pose`."""
    p, q = msg.position, msg.orientation
    return Pose.from_position_orientation([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])


def pose_to_msg(pose: Pose, msg: Any) -> Any:
    """Fill ``msg`` (a ``geometry_msgs/Pose``) from ``pose``; returns ``msg``."""
    (msg.position.x, msg.position.y, msg.position.z) = (float(v) for v in pose.position)
    (msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w) = (float(v) for v in pose.orientation)
    return msg


def joints_from_msg(msg: Any) -> dict[str, float]:
    """``sensor_msgs/JointState`` -> ``{name: position}``."""
    if len(msg.name) != len(msg.position):
        raise ValueError(f"JointState has {len(msg.name)} names but {len(msg.position)} positions")
    return {str(n): float(p) for n, p in zip(msg.name, msg.position)}


def joints_to_msg(joints: Mapping[str, float], msg: Any) -> Any:
    """Fill ``msg`` (a ``sensor_msgs/JointState``) with ``joints``; returns ``msg``."""
    msg.name = list(joints)
    msg.position = [float(v) for v in joints.values()]
    return msg


def covariance_to_ros(covariance: np.ndarray, pose: Pose, centre_obj: np.ndarray) -> list[float]:
    """The tracker's ``covariance [6 + k, 6 + k]`` (the object's box centre's displacement and the
    rotation about that centre, camera axes) as ``PoseWithCovariance.covariance``: 36 values, row-major,
    (x, y, z, rotation about x, y, z) of the pose's origin in the camera frame.

    The origin is ``c - R c_obj``; turning by ``δω`` about the centre moves it by ``δω x (-R c_obj)``,
    so ``δorigin = δc + [R c_obj]x δω``.
    """
    S = np.asarray(covariance, dtype=np.float64)[:6, :6]
    a = pose.matrix[:3, :3] @ np.asarray(centre_obj, dtype=np.float64)
    J = np.eye(6)
    J[:3, 3:] = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return (J @ S @ J.T).ravel().tolist()


def stamp_seconds(stamp: Any) -> float:
    """``builtin_interfaces/Time`` -> seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def main(args: list[str] | None = None) -> int:
    import threading

    import rclpy
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from message_filters import ApproximateTimeSynchronizer, Subscriber
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image, JointState

    from narf_client import NarfClient, NarfError, TrackFrame

    class NarfTracker(Node):
        def __init__(self) -> None:
            super().__init__("narf_tracker")
            url = self.declare_parameter("server_url", "http://127.0.0.1:8000").value
            token = self.declare_parameter("token", "").value or None
            self.model = self.declare_parameter("model", "clamp").value
            self.options = {"iterations": self.declare_parameter("iterations", 10).value}
            use_depth = self.declare_parameter("use_depth", True).value
            self.client = NarfClient(url, token)
            bounds = self.client.model(self.model).bounds
            self.centre = bounds.mean(0) if bounds is not None else np.zeros(3)
            self.camera: tuple[np.ndarray, int, int] | None = None
            self.initial: Pose | None = None
            self.state: str | None = None  # the server's token: all the tracking state there is
            self.busy = threading.Lock()
            self.pose_pub = self.create_publisher(PoseWithCovarianceStamped, "~/pose", 10)
            self.joints_pub = self.create_publisher(JointState, "~/joint_states", 10)
            self.create_subscription(CameraInfo, "camera_info", self.on_camera_info, 10)
            self.create_subscription(PoseStamped, "initial_pose", self.on_initial_pose, 10)
            topics = [Subscriber(self, Image, "image"), Subscriber(self, Image, "mask")]
            if use_depth:
                topics.append(Subscriber(self, Image, "depth"))
            sync = ApproximateTimeSynchronizer(topics, 5, 0.02)
            sync.registerCallback(self.on_frame)

        def on_camera_info(self, msg: CameraInfo) -> None:
            self.camera = camera_info_to_k(msg)

        def on_initial_pose(self, msg: PoseStamped) -> None:
            self.initial, self.state = pose_from_msg(msg.pose), None  # (re)start the track there

        def on_frame(self, image: Image, mask: Image, depth: Image | None = None) -> None:
            if self.camera is None or (self.state is None and self.initial is None):
                return  # no calibration or starting pose yet
            if not self.busy.acquire(blocking=False):
                return  # still working on the previous frame
            threading.Thread(target=self.track, args=(image, mask, depth), daemon=True).start()

        def track(self, image: Image, mask: Image, depth: Image | None) -> None:
            try:
                K, _, _ = self.camera
                frame = TrackFrame(stamp_seconds(image.header.stamp), image_to_array(image), mask_to_array(mask),
                                   None if depth is None else depth_to_metres(depth))
                update = self.client.track_step(frame, K, model=self.model, state=self.state,
                                                initial_pose=self.initial, options=self.options)
            except (NarfError, ValueError) as e:
                self.get_logger().warning(f"track failed: {e}")
                if getattr(e, "field", None) in ("request.state", "request.time"):
                    self.state = None  # e.g. a stamp that went backwards (a bag looped): start again
                return
            finally:
                self.busy.release()
            self.state = update.state
            for warning in update.warnings:  # e.g. a depth in the wrong unit, a joint the view leaves a guess
                self.get_logger().warning(warning, throttle_duration_sec=5.0)
            if update.status == "lost":
                self.get_logger().info(f"lost: {update.reason}")
                return
            out = PoseWithCovarianceStamped()
            out.header = image.header
            pose_to_msg(update.pose, out.pose.pose)
            if update.uncertainty is not None:
                out.pose.covariance = covariance_to_ros(update.uncertainty.covariance, update.pose, self.centre)
            self.pose_pub.publish(out)
            joints = joints_to_msg(update.joints, JointState())
            joints.header = image.header
            self.joints_pub.publish(joints)
            self.get_logger().debug(f"{update.status}, {update.seconds * 1000:.0f} ms")

    rclpy.init(args=args)
    node = NarfTracker()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.client.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
