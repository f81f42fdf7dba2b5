"""Write RealSense `.bag` recordings (librealsense rosbag layout, file version 4) with `rosbags`.

The file plays through pyrealsense2 exactly like a bag recorded by the RealSense Viewer
(`rs.config.enable_device_from_file`), with its own depth intrinsics and depth-to-colour extrinsics,
so `rs.align` does real work on it. Uses: test data from the simulator, and `pallet6d record --format bag`.

Facts the layout rests on (librealsense `src/media/ros/ros_file_format.h`, `ros_reader.cpp`):
- static description messages are stamped at ROS time (0 s, 1 ns), frames later;
- `/file_version` (std_msgs/UInt32), `/device_0/info` and `/device_0/sensor_N/info`
  (diagnostic_msgs/KeyValue; the sensor "Name" decides its kind: "Stereo Module", "RGB Camera");
- per stream `<stream>/info` (realsense_msgs/StreamInfo), `<stream>/info/camera_info`
  (sensor_msgs/CameraInfo), `<stream>/tf/0` (geometry_msgs/Transform; without it `rs.align`
  silently assumes identity extrinsics), `<stream>/image/data` (sensor_msgs/Image);
- the depth scale comes from `/device_0/sensor_0/option/Depth Units/value` (std_msgs/Float32);
  without it distances read wrong;
- the reader matches message types by MD5, so realsense_msgs types are registered from their .msg text;
- compressed bags do not play: chunks are written uncompressed.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from pallet6d.runtime.geometry import check_K, invert_T, rot_to_quat

__all__ = ["RealSenseBagWriter", "STREAM_INFO_MSG"]

log = logging.getLogger(__name__)

FILE_VERSION = 4
STATIC_NS = 1  # ros::TIME_MIN: where librealsense looks for the device description
STREAM_INFO_MSG = """\
uint32 fps
string encoding
bool is_recommended
"""
_DEPTH = "/device_0/sensor_0/Depth_0"
_COLOR = "/device_0/sensor_1/Color_0"
_DEPTH_UNITS = "/device_0/sensor_0/option/Depth Units"


def _typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg(STREAM_INFO_MSG, "realsense_msgs/msg/StreamInfo"))
    return store


class RealSenseBagWriter:
    """Write a D435-like device with a depth and a colour stream to a `.bag` file.

    :param path: output file (overwritten).
    :param color_size_wh: colour image (width, height).
    :param K_color: (3, 3) colour intrinsics.
    :param depth_size_wh: depth image (width, height); defaults to the colour size.
    :param K_depth: (3, 3) depth intrinsics; defaults to `K_color`.
    :param T_color_depth: (4, 4) maps depth-camera points into the colour camera frame (metres);
        identity for depth that is already registered to colour.
    :param depth_scale_m: metres per depth unit ("Depth Units" option).
    :param fps: nominal frame rate written into the stream info.
    :param serial: device serial number written into the device info.
    """

    def __init__(self, path: str | Path, color_size_wh: tuple[int, int], K_color: np.ndarray,
                 depth_size_wh: tuple[int, int] | None = None, K_depth: np.ndarray | None = None,
                 T_color_depth: np.ndarray | None = None, depth_scale_m: float = 0.001, fps: int = 30,
                 serial: str = "000000000000", name: str = "Intel RealSense D435") -> None:
        from rosbags.rosbag1 import Writer  # dev/realsense tooling only, not needed to play
        self.path = Path(path)
        self.color_size_wh = tuple(int(v) for v in color_size_wh)
        self.depth_size_wh = tuple(int(v) for v in (depth_size_wh or color_size_wh))
        self.K_color = check_K(K_color)
        self.K_depth = check_K(self.K_color if K_depth is None else K_depth)
        T = np.eye(4) if T_color_depth is None else np.asarray(T_color_depth, dtype=np.float64)
        if T.shape != (4, 4) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6):
            raise ValueError(f"T_color_depth must be a (4, 4) rigid transform, got shape {T.shape}")
        if not depth_scale_m > 0:
            raise ValueError(f"depth_scale_m must be positive, got {depth_scale_m}")
        self.T_color_depth = T
        self.depth_scale_m = float(depth_scale_m)
        self.fps = int(fps)
        self._store = _typestore()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists():
            self.path.unlink()
        self._bag = Writer(self.path)  # rosbags writes uncompressed chunks unless told otherwise
        self._bag.open()
        self._conns: dict[str, object] = {}
        self._t0_s: float | None = None
        self.n_frames = 0
        self._write_description(serial, name)

    # -- low level -----------------------------------------------------------------------------
    def _msg(self, typename: str, **fields):
        return self._store.types[typename](**fields)

    def _put(self, topic: str, typename: str, t_ns: int, msg) -> None:
        conn = self._conns.get(topic)
        if conn is None:
            conn = self._conns[topic] = self._bag.add_connection(topic, typename, typestore=self._store)
        self._bag.write(conn, int(t_ns), self._store.serialize_ros1(msg, typename))

    def _keyvalue(self, topic: str, key: str, value: str) -> None:
        self._put(topic, "diagnostic_msgs/msg/KeyValue", STATIC_NS,
                  self._msg("diagnostic_msgs/msg/KeyValue", key=key, value=value))

    def _header(self, seq: int, stamp_s: float):
        sec = int(np.floor(stamp_s))
        nsec = int(round((stamp_s - sec) * 1e9))
        if nsec >= 1_000_000_000:
            sec, nsec = sec + 1, nsec - 1_000_000_000
        time = self._store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        return self._msg("std_msgs/msg/Header", seq=int(seq), stamp=time, frame_id="0")

    # -- description ---------------------------------------------------------------------------
    def _write_description(self, serial: str, name: str) -> None:
        self._put("/file_version", "std_msgs/msg/UInt32", STATIC_NS, self._msg("std_msgs/msg/UInt32", data=FILE_VERSION))
        for key, value in (("Name", name), ("Serial Number", serial), ("Product Id", "0B07"),
                           ("Product Line", "D400"), ("Firmware Version", "5.16.0.1")):
            self._keyvalue("/device_0/info", key, value)
        self._keyvalue("/device_0/sensor_0/info", "Name", "Stereo Module")
        self._keyvalue("/device_0/sensor_1/info", "Name", "RGB Camera")
        self._put(f"{_DEPTH_UNITS}/value", "std_msgs/msg/Float32", STATIC_NS,
                  self._msg("std_msgs/msg/Float32", data=self.depth_scale_m))
        self._put(f"{_DEPTH_UNITS}/description", "std_msgs/msg/String", STATIC_NS,
                  self._msg("std_msgs/msg/String", data="Number of meters represented by a single depth unit"))
        # Extrinsics group 0, reference = the colour stream. Each stream's tf/0 holds the transform that
        # maps reference-frame points into the stream frame (measured: writing T_color_depth there makes
        # pyrealsense2 report its inverse as depth->colour; the bag round-trip test checks this).
        self._stream_description(_DEPTH, "mono16", self.depth_size_wh, self.K_depth, invert_T(self.T_color_depth))
        self._stream_description(_COLOR, "rgb8", self.color_size_wh, self.K_color, np.eye(4))

    def _stream_description(self, prefix: str, encoding: str, size_wh, K: np.ndarray, T_stream_ref: np.ndarray) -> None:
        self._put(f"{prefix}/info", "realsense_msgs/msg/StreamInfo", STATIC_NS,
                  self._msg("realsense_msgs/msg/StreamInfo", fps=self.fps, encoding=encoding, is_recommended=True))
        w, h = size_wh
        roi = self._msg("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        info = self._msg("sensor_msgs/msg/CameraInfo", header=self._header(0, 0.0), height=h, width=w,
                         distortion_model="None", D=np.zeros(5), K=K.reshape(9).astype(np.float64),
                         R=np.eye(3).reshape(9), P=np.hstack([K, np.zeros((3, 1))]).reshape(12),
                         binning_x=0, binning_y=0, roi=roi)
        self._put(f"{prefix}/info/camera_info", "sensor_msgs/msg/CameraInfo", STATIC_NS, info)
        qw, qx, qy, qz = rot_to_quat(T_stream_ref[:3, :3])
        tf = self._msg("geometry_msgs/msg/Transform",
                       translation=self._msg("geometry_msgs/msg/Vector3", x=float(T_stream_ref[0, 3]),
                                             y=float(T_stream_ref[1, 3]), z=float(T_stream_ref[2, 3])),
                       rotation=self._msg("geometry_msgs/msg/Quaternion", x=float(qx), y=float(qy), z=float(qz),
                                          w=float(qw)))
        self._put(f"{prefix}/tf/0", "geometry_msgs/msg/Transform", STATIC_NS, tf)

    # -- frames --------------------------------------------------------------------------------
    def write(self, rgb: np.ndarray, depth: np.ndarray, timestamp_s: float, frame_number: int) -> None:
        """Append one frame pair (captured together).

        :param rgb: (H, W, 3) uint8 RGB at the colour size.
        :param depth: (h, w) uint16 depth in depth units, in the depth camera's own image.
        :param timestamp_s: device time of the capture, seconds.
        """
        w, h = self.color_size_wh
        dw, dh = self.depth_size_wh
        rgb = np.ascontiguousarray(rgb)
        depth = np.ascontiguousarray(depth)
        if rgb.shape != (h, w, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be ({h}, {w}, 3) uint8, got {rgb.shape} {rgb.dtype}")
        if depth.shape != (dh, dw) or depth.dtype != np.uint16:
            raise ValueError(f"depth must be ({dh}, {dw}) uint16, got {depth.shape} {depth.dtype}")
        if self._t0_s is None:
            self._t0_s = float(timestamp_s)
        # bag time: 1 s after the static description, then the capture clock
        t_ns = 1_000_000_000 + int(round((float(timestamp_s) - self._t0_s) * 1e9))
        if t_ns <= STATIC_NS:
            raise ValueError(f"timestamps must not go back before the first frame ({timestamp_s} < {self._t0_s})")
        stamp_s = float(timestamp_s)
        for prefix, enc, img, step in ((_DEPTH, "mono16", depth, dw * 2), (_COLOR, "rgb8", rgb, w * 3)):
            msg = self._msg("sensor_msgs/msg/Image", header=self._header(frame_number, stamp_s),
                            height=img.shape[0], width=img.shape[1], encoding=enc, is_bigendian=0, step=step,
                            data=np.frombuffer(img.astype(img.dtype.newbyteorder("<"), copy=False).tobytes(),
                                               dtype=np.uint8))
            self._put(f"{prefix}/image/data", "sensor_msgs/msg/Image", t_ns, msg)
        self.n_frames += 1

    def close(self) -> None:
        if self._bag is not None:
            self._bag.close()
            self._bag = None
            log.info("wrote %d frames to %s", self.n_frames, self.path)

    def __enter__(self) -> "RealSenseBagWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
