"""The replay folder format: writer and player (`replay:DIR`).

Layout (version 1)::

    DIR/
      camera.json          what is below, plus the frame list
      rgb/000000.png       colour, 8-bit RGB (stored as PNG or JPEG; OpenCV writes BGR order on disk
                           as every image viewer expects)
      depth/000000.png     16-bit single-channel PNG, depth aligned to the colour image, in units of
                           depth_scale_m metres, 0 = no data

camera.json::

    {"format": "pallet6d-replay", "version": 1,
     "width": 848, "height": 480,            colour (= depth) image size
     "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
     "depth_scale_m": 0.001,                 metres per depth unit
     "source": "realsense:123456789012",     where it was recorded (free text)
     "frames": [{"rgb": "rgb/000000.png", "depth": "depth/000000.png",
                 "timestamp_s": 12.345, "frame_number": 0}, ...]}

The writer rewrites camera.json atomically every `flush_every` frames, so a recording cut short by a
crash or power loss still plays up to its last flush.
"""
from __future__ import annotations

import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from pallet6d.runtime.geometry import check_K
from pallet6d.runtime.inputs import check_image_size

from .base import FrameSource
from .errors import CameraError, CameraNotFound, FrameReadError
from .frame import RGBDFrame

__all__ = ["REPLAY_FORMAT", "ReplayWriter", "ReplaySource", "read_frame_files", "ON_ERROR_MODES", "check_on_error"]

log = logging.getLogger(__name__)

REPLAY_FORMAT = "pallet6d-replay"
REPLAY_VERSION = 1
ON_ERROR_MODES = ("skip", "raise")


def check_on_error(on_error: str) -> str:
    """A recording player's `on_error`, checked: one of `ON_ERROR_MODES`. :raises ValueError: another value."""
    if on_error not in ON_ERROR_MODES:
        raise ValueError(f"on_error must be one of {ON_ERROR_MODES}, got {on_error!r}")
    return on_error


class ReplayWriter:
    """Write `RGBDFrame`s to a replay folder.

    :param out_dir: folder to create (must not already hold a recording unless `overwrite`).
    :param rgb_format: "png" (lossless) or "jpg" (about 10x smaller, lossy).
    :param jpeg_quality: 1..100 for "jpg".
    :param flush_every: rewrite camera.json after this many frames.
    """

    def __init__(self, out_dir: str | Path, rgb_format: str = "png", jpeg_quality: int = 95,
                 flush_every: int = 30, overwrite: bool = False) -> None:
        if rgb_format not in ("png", "jpg"):
            raise ValueError(f"rgb_format must be 'png' or 'jpg', got {rgb_format!r}")
        if not 1 <= int(jpeg_quality) <= 100:
            raise ValueError(f"jpeg_quality must be in 1..100, got {jpeg_quality}")
        self.out_dir = Path(out_dir)
        if (self.out_dir / "camera.json").exists() and not overwrite:
            raise FileExistsError(f"{self.out_dir} already holds a recording (camera.json); choose another folder "
                                  "or overwrite it (overwrite=True, `pallet6d record --overwrite`)")
        (self.out_dir / "rgb").mkdir(parents=True, exist_ok=True)
        (self.out_dir / "depth").mkdir(parents=True, exist_ok=True)
        self.rgb_format = rgb_format
        self.jpeg_quality = int(jpeg_quality)
        self.flush_every = max(1, int(flush_every))
        self._header: dict | None = None
        self._frames: list[dict] = []

    def __enter__(self) -> "ReplayWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def n_frames(self) -> int:
        return len(self._frames)

    def write(self, frame: RGBDFrame) -> None:
        """Append one frame. All frames of a recording share image size, K and depth scale."""
        header = {"width": frame.width, "height": frame.height, "K": frame.K.tolist(),
                  "depth_scale_m": frame.depth_scale_m}
        if self._header is None:
            self._header = dict(header, source=frame.source)
        elif any(self._header[k] != v for k, v in header.items()):
            raise ValueError(f"frame {frame.frame_number} changes image size, K or depth scale mid-recording "
                             f"({ {k: v for k, v in header.items() if self._header[k] != v} }); "
                             "start a new recording folder for a new camera setting")
        i = len(self._frames)
        rgb_rel = f"rgb/{i:06d}.{self.rgb_format}"
        depth_rel = f"depth/{i:06d}.png"
        bgr = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)
        params = [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality] if self.rgb_format == "jpg" else []
        if not cv2.imwrite(str(self.out_dir / rgb_rel), bgr, params):
            raise OSError(f"cannot write {self.out_dir / rgb_rel}")
        if not cv2.imwrite(str(self.out_dir / depth_rel), frame.depth):
            raise OSError(f"cannot write {self.out_dir / depth_rel}")
        self._frames.append({"rgb": rgb_rel, "depth": depth_rel, "timestamp_s": frame.timestamp_s,
                             "frame_number": frame.frame_number})
        if len(self._frames) % self.flush_every == 0:
            self._flush()

    def close(self) -> None:
        if self._header is not None:
            self._flush()

    def _flush(self) -> None:
        assert self._header is not None
        doc = {"format": REPLAY_FORMAT, "version": REPLAY_VERSION, **self._header, "frames": self._frames}
        tmp = self.out_dir / "camera.json.tmp"
        tmp.write_text(json.dumps(doc, indent=1))
        os.replace(tmp, self.out_dir / "camera.json")  # atomic: a reader never sees half a file


def _load_index(root: Path) -> dict:
    path = root / "camera.json"
    if not root.is_dir():
        raise CameraNotFound(f"replay folder {root} does not exist")
    if not path.is_file():
        raise CameraNotFound(f"{root} is not a replay folder: no camera.json")
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CameraError(f"{path}: cannot read: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != REPLAY_FORMAT:
        raise CameraError(f"{path}: not a {REPLAY_FORMAT} index (format={doc.get('format') if isinstance(doc, dict) else None!r})")
    if doc.get("version") != REPLAY_VERSION:
        raise CameraError(f"{path}: unsupported replay version {doc.get('version')!r} (this pallet6d reads {REPLAY_VERSION})")
    try:
        for key in ("width", "height"):
            if not _is_int(doc[key]) or doc[key] <= 0:
                raise ValueError(f"{key} must be a positive integer, got {doc[key]!r}")
        check_image_size(doc["height"], doc["width"])
        doc["K"] = check_K(doc["K"], (doc["height"], doc["width"]))
        if not _is_number(doc["depth_scale_m"]) or not doc["depth_scale_m"] > 0:
            raise ValueError(f"depth_scale_m must be a positive number, got {doc['depth_scale_m']!r}")
        doc["depth_scale_m"] = float(doc["depth_scale_m"])
        frames = doc["frames"]
        if not isinstance(frames, list):
            raise ValueError("frames must be a list")
    except KeyError as exc:
        raise CameraError(f"{path}: invalid replay index: missing {exc}") from None
    except (TypeError, ValueError) as exc:
        raise CameraError(f"{path}: invalid replay index: {exc}") from None
    doc["frames"] = [_frame_entry(i, f) for i, f in enumerate(frames)]
    return doc


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _rel_path(v) -> bool:
    """A file name inside the recording: relative, without '..'."""
    return isinstance(v, str) and bool(v) and not Path(v).is_absolute() and ".." not in Path(v).parts


def _frame_entry(i: int, f) -> dict:
    """One frame entry of camera.json, checked: rgb, depth (paths inside the folder), timestamp_s (finite
    seconds), frame_number (int >= 0; the entry's position when absent) and `error`, the reason it cannot be
    played (None when it can). A bad entry is one unreadable frame, not an unreadable recording."""
    if not isinstance(f, dict):
        return {"frame_number": i, "timestamp_s": None, "error": f"frame entry {i} is not an object: {f!r:.60}"}
    fn = f.get("frame_number", i)
    out = {"rgb": f.get("rgb"), "depth": f.get("depth"), "timestamp_s": f.get("timestamp_s"),
           "frame_number": fn if _is_int(fn) and fn >= 0 else i, "error": None}
    problems = [f"{k} must be a file name inside the recording, got {f.get(k)!r:.60}" for k in ("rgb", "depth")
                if not _rel_path(f.get(k))]
    if not _is_number(f.get("timestamp_s")):
        problems.append(f"timestamp_s must be a finite number of seconds, got {f.get('timestamp_s')!r:.60}")
        out["timestamp_s"] = None
    if not (_is_int(fn) and fn >= 0):
        problems.append(f"frame_number must be an integer >= 0, got {fn!r:.60}")
    if problems:
        out["error"] = f"frame entry {i}: " + "; ".join(problems)
    return out


def _imread(path: Path, flags: int) -> np.ndarray:
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise FrameReadError(f"{path}: cannot read: {exc.strerror or exc}") from None
    img = cv2.imdecode(data, flags) if data.size else None
    if img is None:
        raise FrameReadError(f"{path}: not a readable image (corrupt or truncated)")
    return img


def read_frame_files(rgb_path: Path, depth_path: Path, size_wh: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Read one colour + depth pair of a replay folder.

    :return: rgb (H, W, 3) uint8 RGB, depth (H, W) uint16.
    :raises FrameReadError: missing, corrupt, truncated or wrongly shaped files.
    """
    bgr = _imread(rgb_path, cv2.IMREAD_COLOR)
    depth = _imread(depth_path, cv2.IMREAD_UNCHANGED)
    w, h = size_wh
    if bgr.shape[:2] != (h, w):
        raise FrameReadError(f"{rgb_path}: size {bgr.shape[1]}x{bgr.shape[0]} differs from camera.json's {w}x{h}")
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise FrameReadError(f"{depth_path}: depth must be a 16-bit single-channel PNG, got {depth.dtype} {depth.shape}")
    if depth.shape != (h, w):
        raise FrameReadError(f"{depth_path}: size {depth.shape[1]}x{depth.shape[0]} differs from camera.json's {w}x{h}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth


class ReplaySource(FrameSource):
    """Play a replay folder.

    :param root: the folder (with camera.json).
    :param realtime: pace frames by their recorded timestamps (times 1/`speed`); else as fast as read.
    :param loop: start over at the end (frame numbers and timestamps keep increasing).
    :param on_error: "skip" a missing/corrupt/truncated frame (or a bad entry of camera.json) with a warning,
        or "raise" `FrameReadError` with its `frame_number`; the next `read()` goes on with the next frame.
    """

    def __init__(self, root: str | Path, realtime: bool = False, loop: bool = False, on_error: str = "skip",
                 speed: float = 1.0, _clock: Callable[[], float] = time.monotonic,
                 _sleep: Callable[[float], None] = time.sleep) -> None:
        check_on_error(on_error)
        if not speed > 0:
            raise ValueError(f"speed must be positive, got {speed}")
        self.root = Path(root)
        super().__init__(f"replay:{self.root}")
        self.realtime, self.loop, self.on_error, self.speed = bool(realtime), bool(loop), on_error, float(speed)
        self._clock, self._sleep = _clock, _sleep
        self._entries: list[dict] = []
        self._size_wh = (0, 0)
        self.recorded_source = ""
        self.skipped = 0  #: frames skipped because of read errors (all passes)

    def __len__(self) -> int:
        """Frames listed in the recording (one pass), known after start()."""
        return len(self._entries)

    def _start(self) -> None:
        doc = _load_index(self.root)
        self._K, self._depth_scale_m = doc["K"], doc["depth_scale_m"]
        self._size_wh = (doc["width"], doc["height"])
        self._entries = doc["frames"]
        self.recorded_source = str(doc.get("source", ""))
        if not self._entries:
            log.warning("%s: the recording holds no frames", self.name)
        self._pos = 0
        self._pass = 0
        self._pass_yielded = 0
        self._t_offset = 0.0
        self._fn_offset = 0
        self._t0_rec: float | None = None
        self._t0_wall = 0.0

    def _stop(self) -> None:
        pass

    def _next_pass(self) -> bool:
        if not self.loop or not self._entries:
            return False
        if self._pass_yielded == 0:
            raise FrameReadError(f"{self.name}: no readable frame in the whole recording")
        ts = [e["timestamp_s"] for e in self._entries if e["timestamp_s"] is not None]
        period = (ts[-1] - ts[0]) / (len(ts) - 1) if len(ts) > 1 else 1 / 30
        self._t_offset += (ts[-1] - ts[0] if ts else 0.0) + period
        self._fn_offset += max(e["frame_number"] for e in self._entries) + 1
        self._pos, self._pass, self._pass_yielded = 0, self._pass + 1, 0
        return True

    def _read(self) -> RGBDFrame | None:
        while True:
            if self._pos >= len(self._entries) and not self._next_pass():
                return None
            i = self._pos
            self._pos += 1
            entry = self._entries[i]
            number = entry["frame_number"] + self._fn_offset
            try:
                if entry["error"] is not None:
                    raise FrameReadError(f"{self.root / 'camera.json'}: {entry['error']}", number)
                rgb, depth = read_frame_files(self.root / entry["rgb"], self.root / entry["depth"], self._size_wh)
            except FrameReadError as exc:
                if self.on_error == "raise":
                    raise FrameReadError(str(exc), number) from None
                self.skipped += 1
                log.warning("%s: skipping frame %d: %s", self.name, number, exc)
                continue
            self._pass_yielded += 1
            t = entry["timestamp_s"] + self._t_offset
            self._pace(t)
            return RGBDFrame(rgb, depth, self._K, self._depth_scale_m, t, number, self.name)

    def _pace(self, t_rec: float) -> None:
        if not self.realtime:
            return
        now = self._clock()
        if self._t0_rec is None:
            self._t0_rec, self._t0_wall = t_rec, now
            return
        wait = self._t0_wall + (t_rec - self._t0_rec) / self.speed - now
        if wait > 0:
            self._sleep(wait)
