"""RealSense .bag round trip: sim frames -> rosbags writer -> pyrealsense2 playback with real alignment."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

pytest.importorskip("rosbags")
rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 (extra 'realsense') is not installed")

from pallet6d.runtime.bop import BopDataset  # noqa: E402
from pallet6d.runtime.cameras import CameraNotFound, RGBDFrame, open_source  # noqa: E402
from pallet6d.runtime.cameras.realsense import RealSenseCamera  # noqa: E402
from pallet6d.runtime.cameras.rsbag import RealSenseBagWriter  # noqa: E402
from pallet6d.runtime.cli import main as cli_main  # noqa: E402
from pallet6d.runtime.geometry import backproject_depth, invert_T, make_T, quat_to_rot, transform_points  # noqa: E402


@pytest.fixture(scope="module")
def sim_frames(tmp_path_factory):
    root = tmp_path_factory.mktemp("sim")
    assert cli_main(["sim", "--preset", "virtual-clean", "--frames", "3", "--seed", "5", "--size", "320x240",
                     "--out", str(root)]) == 0
    ds = BopDataset(root)
    return [ds[i] for i in range(len(ds))]


def render_depth(depth_m: np.ndarray, K_color: np.ndarray, T_depth_color: np.ndarray, K_depth: np.ndarray,
                 size_wh: tuple[int, int], scale_m: float = 0.001) -> np.ndarray:
    """Depth image of a second camera seeing the points of a colour-registered depth map (z-buffered).

    :return: (h, w) uint16 in `scale_m` units, 0 = no data.
    """
    pts = backproject_depth(depth_m, K_color).reshape(-1, 3)
    pts = pts[pts[:, 2] > 0]
    p = transform_points(T_depth_color, pts)
    u = np.rint(K_depth[0, 0] * p[:, 0] / p[:, 2] + K_depth[0, 2]).astype(int)
    v = np.rint(K_depth[1, 1] * p[:, 1] / p[:, 2] + K_depth[1, 2]).astype(int)
    w, h = size_wh
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    z = np.full((h, w), np.inf)
    np.minimum.at(z, (v[ok], u[ok]), p[ok, 2])
    z[~np.isfinite(z)] = 0
    return np.rint(z / scale_m).astype(np.uint16)


# depth camera: its own focal length and principal point, 15 mm baseline and a small rotation (D435-like)
T_COLOR_DEPTH = make_T(quat_to_rot(np.array([1.0, 0.004, -0.006, 0.002]) / np.linalg.norm([1.0, 0.004, -0.006, 0.002])),
                       np.array([0.015, 0.0005, -0.001]))


def _write_bag(path, frames, identity: bool):
    f0 = frames[0]
    h, w = f0.depth_m.shape
    if identity:
        K_depth, size_d, T = f0.K, (w, h), np.eye(4)
    else:
        # same size (half resolution would blur the thin pallet boards and test resampling, not alignment)
        K_depth = np.array([[f0.K[0, 0] * 0.97, 0, f0.K[0, 2] + 3.3], [0, f0.K[1, 1] * 0.97, f0.K[1, 2] - 2.6], [0, 0, 1]])
        size_d, T = (w, h), T_COLOR_DEPTH
    depths = []
    with RealSenseBagWriter(path, (w, h), f0.K, size_d, K_depth, T, depth_scale_m=0.001, fps=30,
                            serial="987654321") as bag:
        for i, f in enumerate(frames):
            depths.append(render_depth(f.depth_m, f.K, invert_T(T), K_depth, size_d))
            bag.write(f.rgb, depths[-1], timestamp_s=50.0 + i / 30, frame_number=7 + i)
    return K_depth, size_d, depths


def test_bag_plays_with_alignment(tmp_path, sim_frames):
    path = tmp_path / "sim.bag"
    K_depth, size_d, raw_depths = _write_bag(path, sim_frames, identity=False)

    # the bag carries the depth camera's own intrinsics and the extrinsics, as a real D435 bag does (read from the
    # recorded stream profiles; nothing streams, so no SDK thread outlives the check)
    ctx = rs.context()
    device = ctx.load_device(str(path))
    try:
        profiles = {p.stream_type(): p.as_video_stream_profile() for s in device.query_sensors()
                    for p in s.get_stream_profiles()}
        dprof, cprof = profiles[rs.stream.depth], profiles[rs.stream.color]
        di = dprof.get_intrinsics()
        assert (di.width, di.height) == size_d and di.fx == pytest.approx(K_depth[0, 0])
        ext = dprof.get_extrinsics_to(cprof)
        np.testing.assert_allclose(np.array(ext.rotation).reshape(3, 3).T, T_COLOR_DEPTH[:3, :3], atol=1e-6)
        np.testing.assert_allclose(ext.translation, T_COLOR_DEPTH[:3, 3], atol=1e-7)
    finally:
        del device
        ctx.unload_device(str(path))

    with open_source(f"bag:{path}") as cam:
        assert isinstance(cam, RealSenseCamera) and not cam.live
        np.testing.assert_allclose(cam.K, sim_frames[0].K, rtol=1e-6)  # before the first frame
        assert cam.depth_scale_m == pytest.approx(0.001)
        assert cam.device_serial == "987654321"
        frames = list(cam)
    assert len(frames) == len(sim_frames)
    assert [f.frame_number for f in frames] == [7, 8, 9]
    np.testing.assert_allclose([f.timestamp_s for f in frames], [50.0, 50.0 + 1 / 30, 50.0 + 2 / 30], atol=1e-6)

    raw_errors, aligned_errors = [], []
    for got, ref, raw in zip(frames, sim_frames, raw_depths):
        assert isinstance(got, RGBDFrame)
        np.testing.assert_array_equal(got.rgb, ref.rgb)
        assert got.depth.shape == ref.depth_m.shape
        d_got, d_ref, d_raw = got.depth_m, ref.depth_m, raw * np.float32(0.001)
        both = (d_ref > 0) & (d_got > 0)
        assert both.sum() >= 0.9 * (d_ref > 0).sum()
        assert np.median(np.abs(d_got[both] - d_ref[both])) <= 0.003  # resampling: a neighbour's value at most
        for gt in ref.gts:  # each pallet's depth lands on its own colour pixels again
            m = gt.mask_visib & (d_ref > 0)
            if m.sum() < 100:
                continue
            valid = m & (d_got > 0)
            assert valid.sum() >= 0.7 * m.sum()  # thin boards, partly occluded from the depth camera
            aligned_errors.append(np.median(np.abs(d_got[valid] - d_ref[valid])))
            raw_ok = m & (d_raw > 0)
            if raw_ok.any():
                raw_errors.append(np.median(np.abs(d_raw[raw_ok] - d_ref[raw_ok])))
    aligned_errors, raw_errors = np.array(aligned_errors), np.array(raw_errors)
    assert len(aligned_errors) >= 3
    # a few pallets sit behind others as the depth camera sees them (15 mm baseline): their edges differ
    assert np.median(aligned_errors) <= 0.005 and np.mean(aligned_errors <= 0.01) >= 0.75
    # without alignment the same check fails: the bag's depth image really is another camera's
    assert np.median(raw_errors) >= 0.03


def test_identity_alignment_keeps_values(tmp_path, sim_frames):
    path = tmp_path / "registered.bag"
    _write_bag(path, sim_frames[:2], identity=True)
    with RealSenseCamera(bag_path=path) as cam:
        frames = list(cam)
    assert len(frames) == 2
    for got, ref in zip(frames, sim_frames):
        expected = np.rint(np.where(ref.depth_m > 0, ref.depth_m, 0) / 0.001).astype(np.uint16)
        # rs.align leaves thin seams of zeros (float rounding of pixel footprints) even between identical
        # cameras, and at depth edges a pixel may take its neighbour's value; all others are exact
        written = got.depth > 0
        assert np.mean(got.depth[written] == expected[written]) >= 0.99
        assert written.sum() >= 0.9 * (expected > 0).sum()


def test_bag_filters_run(tmp_path, sim_frames):
    path = tmp_path / "f.bag"
    _write_bag(path, sim_frames[:2], identity=True)
    with RealSenseCamera(bag_path=path, filters=("decimation", "spatial", "temporal", "hole_filling")) as cam:
        frames = list(cam)
    assert len(frames) == 2 and frames[0].depth.shape == sim_frames[0].depth_m.shape
    # hole filling leaves fewer empty pixels than the raw image has
    assert (frames[1].depth == 0).mean() <= (sim_frames[1].depth_m == 0).mean() + 1e-9


def test_bag_slow_reader_gets_every_frame_in_order(tmp_path, sim_frames):
    # a recording replayed for evaluation: every frameset, first included, however slow the estimator
    path = tmp_path / "slow.bag"
    frames = (sim_frames * 3)[:7]
    _write_bag(path, frames, identity=True)
    numbers = []
    with RealSenseCamera(bag_path=path) as cam:
        for frame in cam:
            numbers.append(frame.frame_number)
            time.sleep(0.1)
    assert numbers == list(range(7, 14))


def test_bag_closed_early_does_not_hang(tmp_path, sim_frames):
    # a daemon stopped mid-recording: the playback is blocked on the full queue when the sensors stop
    # (an SDK syncer in that place deadlocks; CI hung on it)
    path = tmp_path / "early.bag"
    _write_bag(path, (sim_frames * 4)[:12], identity=True)
    for n_read in (0, 1, 3):
        cam = RealSenseCamera(bag_path=path)
        cam.start()
        numbers = [cam.read().frame_number for _ in range(n_read)]
        assert numbers == list(range(7, 7 + n_read))
        closer = threading.Thread(target=cam.stop, daemon=True)
        closer.start()
        closer.join(timeout=30)
        assert not closer.is_alive(), f"stop() hung after {n_read} frames"


def test_missing_bag_and_bad_options(tmp_path):
    with pytest.raises(CameraNotFound, match="does not exist"):
        open_source(f"bag:{tmp_path / 'nope.bag'}").start()
    with pytest.raises(CameraNotFound, match="is a folder, not a .bag file"):
        open_source(f"bag:{tmp_path}").start()
    with pytest.raises(ValueError, match="unknown depth filter"):
        RealSenseCamera(filters=("median",))
