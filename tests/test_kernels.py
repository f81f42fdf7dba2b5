"""The compiled kernels: built where a C compiler is, the same results as refinement's numpy path."""
import dataclasses
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from pallet6d.runtime import kernels
from pallet6d.runtime.geometry import make_T, quat_to_rot
from pallet6d.runtime.refine import (_ICP_DEFAULTS, RefineGeometry, RefineOptions, _icp, box_points, default_starts,
                                     offsets_from_starts, refine_batch)

sim_generate = pytest.importorskip("pallet6d.sim.generate")
from pallet6d.sim.pallets import get_pallet_model  # noqa: E402
from pallet6d.sim.presets import get_preset  # noqa: E402

EPAL = get_pallet_model("epal")
GEOM = RefineGeometry(EPAL.surface_points(1000, seed=0), EPAL.boxes_m)
needs_kernel = pytest.mark.skipif(not kernels.available(),
                                  reason="the compiled kernels are not built here")


def test_the_kernel_is_built_where_a_c_compiler_is():
    """An install on a machine with a C compiler (this test run's) builds and loads the kernel; refinement in
    numpy is only for machines without one."""
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler on this machine")
    path = kernels.library_path()
    assert path is not None, "pip install -e . did not build pallet6d.runtime._kernels"
    assert kernels.available()
    source = Path(kernels.__file__).with_name("kernels.c")
    if source.is_file():                      # a source checkout: the library must be built from today's source
        assert Path(path).stat().st_mtime >= source.stat().st_mtime, \
            "runtime/kernels.c is newer than its build: run make setup (or pip install -e .)"


def _turn(yaw_deg, shift_m):
    a = np.deg2rad(yaw_deg) / 2
    return make_T(quat_to_rot(np.array([np.cos(a), 0, 0, np.sin(a)])), np.asarray(shift_m, float))


@pytest.fixture(scope="module")
def icp_inputs():
    """ICP runs as refinement makes them: a frame's pallets, each from poses off by up to 20 degrees and 12 cm,
    on its box's depth points (pallet, floor, rack, load), zero-padded to a common length; one pallet without
    points, one with too few."""
    rng = np.random.default_rng(5)
    T0, rows = [], []
    for name, seed in (("virtual-clean", 0), ("virtual-occluded", 2), ("indoor-noisy", 3)):
        frame = sim_generate.generate_frame(get_preset(name), seed=seed)
        for g in sorted((g for g in frame.pallets if g.bbox_visib_xywh is not None and g.visib_fract >= 0.1),
                        key=lambda g: -g.visib_fract)[:3]:
            x, y, w, h = g.bbox_visib_xywh
            pts = box_points(frame.depth_m, frame.K, np.array([x, y, x + w, y + h], float), 600, (0.1, 10.0))
            for _ in range(3):
                T0.append(g.T_cam_pallet @ _turn(rng.uniform(-20, 20), rng.uniform(-0.12, 0.12, 3) * [1, 1, 0.25]))
                rows.append(pts)
    T0 += [T0[0], T0[1]]
    rows += [np.zeros((0, 3)), rows[0][:10]]
    n_pts = np.array([len(r) for r in rows])
    pts = np.zeros((len(rows), n_pts.max(), 3))
    for i, r in enumerate(rows):
        pts[i, :len(r)] = r
    return np.stack(T0), pts, n_pts


def _runs(T0, pts, n_pts, stop_near=None, stop_near_m=0.0, prior=(0.1, 0.1), threads=1, iterations=20):
    args = (T0, pts, n_pts, EPAL.boxes_m, iterations, *_ICP_DEFAULTS[:2], *prior, *_ICP_DEFAULTS[4:], stop_near,
            stop_near_m)
    return _icp(*args, compiled=True, threads=threads), _icp(*args, compiled=False)


def _assert_same_runs(a, b, atol_m=5e-4):
    """Same poses to atol_m, same steps, inliers and flags. Not bit for bit: the float32 sums run in another
    order, and a point at the correspondence distance may count in one and not the other, which moves the
    pose by micrometres (the issue's bar for the validation sets is 1 mm)."""
    np.testing.assert_allclose(a.T_cam_pallet, b.T_cam_pallet, atol=atol_m)
    np.testing.assert_array_equal(a.iterations, b.iterations)
    np.testing.assert_array_equal(a.converged, b.converged)
    np.testing.assert_array_equal(a.stopped_near, b.stopped_near)
    np.testing.assert_allclose(a.n_inliers, b.n_inliers, atol=1)
    np.testing.assert_allclose(a.rms_m, b.rms_m, atol=1e-5, equal_nan=True)


@needs_kernel
def test_kernel_runs_icp_as_numpy_does(icp_inputs):
    T0, pts, n_pts = icp_inputs
    kernel, numpy = _runs(T0, pts, n_pts)
    _assert_same_runs(kernel, numpy)
    assert kernel.iterations[-2] == 0 and np.isnan(kernel.rms_m[-2])           # no points: the input pose
    np.testing.assert_array_equal(kernel.T_cam_pallet[-2], T0[-2])
    assert kernel.iterations[-1] == 0                                         # 10 points < min_inliers
    assert kernel.converged.any() and (kernel.iterations > 0).sum() >= len(T0) - 2


@needs_kernel
def test_kernel_stops_near_a_pose_and_takes_per_pose_priors_as_numpy_does(icp_inputs):
    T0, pts, n_pts = icp_inputs
    landed = _runs(T0, pts, n_pts)[1].T_cam_pallet                  # the starts surround ICP's landing
    starts = (landed[:, None] @ offsets_from_starts(default_starts(4))[None]).reshape(-1, 4, 4)
    rep = lambda a: np.repeat(a, 4, axis=0)                                              # noqa: E731
    kernel, numpy = _runs(starts, rep(pts), rep(n_pts), stop_near=rep(landed), stop_near_m=0.005)
    _assert_same_runs(kernel, numpy)
    assert kernel.stopped_near.any() and not kernel.stopped_near.all()
    rng = np.random.default_rng(0)
    rot, trans = rng.uniform(0.01, 0.2, (len(T0), 3)), rng.uniform(0.01, 0.2, (len(T0), 3))
    kernel, numpy = _runs(T0, pts, n_pts, prior=(rot, trans))
    _assert_same_runs(kernel, numpy)


@needs_kernel
def test_kernel_threads_give_the_same_poses(icp_inputs):
    T0, pts, n_pts = icp_inputs
    one, _ = _runs(T0, pts, n_pts)
    for threads in (2, 3, 64):
        many, _ = _runs(T0, pts, n_pts, threads=threads)
        np.testing.assert_array_equal(many.T_cam_pallet, one.T_cam_pallet)
        np.testing.assert_array_equal(many.iterations, one.iterations)


@needs_kernel
def test_kernel_points_inside_boxes_and_zero_steps(icp_inputs):
    """Points inside the boards (depth noise pushes them there) go to the nearest face, as in numpy; with no
    steps the input pose comes back."""
    T0, _, _ = icp_inputs
    rng = np.random.default_rng(1)
    lo, hi = EPAL.boxes_m[:, 0], EPAL.boxes_m[:, 1]
    k = rng.integers(0, len(lo), 400)
    inside_pallet = lo[k] + rng.uniform(0.0, 1.0, (400, 3)) * (hi[k] - lo[k])              # pallet frame
    T = T0[0]
    inside_cam = inside_pallet @ T[:3, :3].T + T[:3, 3]
    pts = np.repeat(inside_cam[None], 2, axis=0)
    kernel, numpy = _runs(np.stack([T, T0[1]]), pts, np.array([400, 400]))
    _assert_same_runs(kernel, numpy)
    kernel, numpy = _runs(T0[:2], pts, np.array([400, 400]), iterations=0)
    np.testing.assert_array_equal(kernel.T_cam_pallet, T0[:2])
    _assert_same_runs(kernel, numpy)


@needs_kernel
def test_refine_batch_compiled_equals_numpy():
    frame = sim_generate.generate_frame(get_preset("virtual-occluded"), seed=2)
    rng = np.random.default_rng(2)
    gts = [g for g in frame.pallets if g.bbox_visib_xywh is not None and g.visib_fract >= 0.1][:4]
    T_net, obs, box_obs = [], [], []
    for g in gts:
        x, y, w, h = g.bbox_visib_xywh
        pts = box_points(frame.depth_m, frame.K, np.array([x, y, x + w, y + h], float), 600, (0.1, 10.0))
        T_net.append(g.T_cam_pallet @ _turn(rng.uniform(-20, 20), rng.uniform(-0.12, 0.12, 3) * [1, 1, 0.25]))
        obs.append(pts[rng.integers(0, len(pts), 200)])
        box_obs.append(pts)
    T_net, obs = np.stack(T_net), np.stack(obs)
    kernel = refine_batch(T_net, obs, box_obs, GEOM, frame.depth_m, frame.K, RefineOptions(threads=2))
    numpy = refine_batch(T_net, obs, box_obs, GEOM, frame.depth_m, frame.K, RefineOptions(compiled=False))
    np.testing.assert_allclose(kernel.T_cam_pallet, numpy.T_cam_pallet, atol=1e-5)
    np.testing.assert_array_equal(kernel.source, numpy.source)
    for a, b in zip(kernel.fits, numpy.fits):
        assert a.score == pytest.approx(b.score, abs=1e-3)


@needs_kernel
def test_kernel_bad_input():
    T0 = np.eye(4)[None]
    with pytest.raises(ValueError, match="boxes"):
        kernels.icp(T0, np.zeros((1, 5, 3)), np.array([5]), np.zeros((kernels.MAX_BOXES + 1, 2, 3)),
                       np.ones(6), 5, 0.08, 0.015, 3, 1e-4, None, 0.0)
    with pytest.raises(ValueError, match="n_pts"):
        kernels.icp(T0, np.zeros((1, 5, 3)), np.array([6]), EPAL.boxes_m, np.ones(6), 5, 0.08, 0.015, 3, 1e-4,
                       None, 0.0)


def test_more_boxes_than_the_kernel_takes_run_in_numpy():
    """A pallet model of more boards than the kernel's limit still refines (numpy); so does every model
    where the kernel is not built."""
    boxes = np.repeat(EPAL.boxes_m, kernels.MAX_BOXES // len(EPAL.boxes_m) + 1, axis=0)
    T0 = make_T(np.eye(3), np.array([0.0, 0.0, 3.0]))[None]
    rng = np.random.default_rng(3)
    pts_pal = EPAL.surface_points(300, seed=1)
    pts = (pts_pal @ T0[0, :3, :3].T + T0[0, :3, 3])[None] + rng.normal(0, 0.001, (1, 300, 3))
    run = _icp(T0 @ _turn(3.0, [0.02, 0.0, 0.0])[None], pts, np.array([300]), boxes, 20, *_ICP_DEFAULTS, None, 0.0)
    assert run.iterations[0] > 0
    assert np.linalg.norm(run.T_cam_pallet[0, :3, 3] - T0[0, :3, 3]) < 0.01


def test_refine_options_threads():
    with pytest.raises(ValueError, match="threads"):
        RefineOptions(threads=0)


def test_without_the_kernel_the_estimator_warns_and_gives_the_same_poses(monkeypatch, caplog):
    """The shipped bundle on a simulated frame: with the kernel, and as on a machine where it was not built."""
    from pallet6d.runtime.estimator import PalletEstimator

    bundle = Path(__file__).resolve().parents[1] / "models" / "epal-default"
    frame = sim_generate.generate_frame(get_preset("virtual-clean"), seed=0)
    compiled = PalletEstimator.from_bundle(bundle, threads=2, precision="int8").estimate(frame.rgb, frame.depth_m,
                                                                                          frame.K)
    monkeypatch.setattr(kernels, "available", lambda: False)
    with caplog.at_level(logging.WARNING, logger="pallet6d.runtime.stage_refine"):
        est = PalletEstimator.from_bundle(bundle, threads=2, precision="int8")
    assert "compiled kernels are not built" in caplog.text
    numpy = est.estimate(frame.rgb, frame.depth_m, frame.K)
    assert len(compiled.poses) == len(numpy.poses) >= 3
    for a, b in zip(compiled.poses, numpy.poses):
        np.testing.assert_allclose(a.T_cam_pallet, b.T_cam_pallet, atol=1e-4)


@pytest.mark.parametrize("model", ["epal", "gma"])
def test_box_grid_lists_the_closest_box_of_every_point(model):
    """Random points over the grid (and on cell borders): the box `closest_on_boxes` picks is in the cell's list."""
    from pallet6d.runtime.refine import _closest, _extents

    boxes = get_pallet_model(model).boxes_m
    grid = kernels.box_grid(boxes, margin_m=0.1, cell_m=0.03)
    rng = np.random.default_rng(4)
    ext = grid.dims * grid.cell_m
    pts = grid.origin_m + rng.uniform(0, 1, (20000, 3)) * ext
    pts[:2000] = grid.origin_m + np.round(pts[:2000] / grid.cell_m) * grid.cell_m - grid.origin_m % grid.cell_m
    pts = pts[np.all((pts >= grid.origin_m) & (pts < grid.origin_m + ext), axis=1)]
    q, _, d = _closest(pts, boxes, _extents(boxes))
    cell = np.floor((pts - grid.origin_m) / grid.cell_m).astype(np.int64)
    flat = np.ravel_multi_index(cell.T, tuple(grid.dims))
    for i in range(len(pts)):
        listed = grid.lists[grid.offsets[flat[i]]:grid.offsets[flat[i] + 1]]
        lo, hi = boxes[listed, 0], boxes[listed, 1]
        on_listed = np.all((q[i] >= lo - 1e-9) & (q[i] <= hi + 1e-9), axis=1)
        assert on_listed.any(), f"point {pts[i]}: its closest point {q[i]} is on no listed box {listed}"
    assert np.all(np.diff(grid.offsets) >= 1) and np.diff(grid.offsets).mean() < 0.25 * len(boxes)


@needs_kernel
def test_kernel_with_the_grid_gives_the_same_runs(icp_inputs):
    T0, pts, n_pts = icp_inputs
    args = (T0, pts, n_pts, EPAL.boxes_m, np.full((len(T0), 6), 100.0), 20, 0.08, 0.015, 30, 1e-4, None, 0.0)
    plain = kernels.icp(*args)
    gridded = kernels.icp(*args, grid=kernels.box_grid(EPAL.boxes_m))
    for a, b in zip(plain, gridded):
        np.testing.assert_array_equal(a, b)


@needs_kernel
def test_kernel_refuses_a_grid_of_other_boxes():
    grid = kernels.box_grid(EPAL.boxes_m)
    with pytest.raises(ValueError, match="grid"):
        kernels.icp(np.eye(4)[None], np.zeros((1, 5, 3)), np.array([5]), EPAL.boxes_m[:3], np.ones(6), 5, 0.08,
                       0.015, 3, 1e-4, None, 0.0, grid=grid)


@pytest.mark.parametrize("boxes, kwargs, match", [
    (np.zeros((0, 2, 3)), {}, "boxes_m"), (np.zeros((2, 3)), {}, "boxes_m"),
    (EPAL.boxes_m, {"cell_m": 0.0}, "cell_m"), (EPAL.boxes_m, {"margin_m": -1.0}, "margin_m")])
def test_box_grid_bad_input(boxes, kwargs, match):
    with pytest.raises(ValueError, match=match):
        kernels.box_grid(boxes, **kwargs)


@pytest.fixture(scope="module")
def fit_inputs():
    """Poses of a frame's pallets (right, and 5-20 cm / degrees off) with the box's depth points as observations,
    and last a pose behind the camera without observations."""
    frame = sim_generate.generate_frame(get_preset("virtual-occluded"), seed=2)
    rng = np.random.default_rng(6)
    T, rows = [], []
    for g in [g for g in frame.pallets if g.bbox_visib_xywh is not None and g.visib_fract >= 0.1][:4]:
        x, y, w, h = g.bbox_visib_xywh
        pts = box_points(frame.depth_m, frame.K, np.array([x, y, x + w, y + h], float), 600, (0.1, 10.0))
        for yaw, shift in ((0.0, 0.0), (5.0, 0.05), (20.0, 0.2)):
            T.append(g.T_cam_pallet @ _turn(rng.choice([-1, 1]) * yaw, rng.uniform(-shift, shift, 3)))
            rows.append(pts[rng.integers(0, len(pts), 256)])
    T.append(make_T(np.eye(3), np.array([0.0, 0.0, -3.0])))
    rows.append(rows[0])
    n_obs = np.array([256] * (len(rows) - 1) + [0])
    return np.stack(T), np.stack(rows), n_obs, frame.depth_m.astype(np.float32), frame.K


@needs_kernel
@pytest.mark.parametrize("mode", ["boxes", "index", "index-and-boxes-pretest", "all-points"])
def test_fit_kernel_scores_as_numpy_does(fit_inputs, mode):
    from pallet6d.runtime.fit import fit_scores

    T, obs, n_obs, depth_m, K = fit_inputs
    kw = {"boxes": {"model_boxes_m": EPAL.boxes_m},
          "index": {"point_index": GEOM.point_index(0.04)},
          "index-and-boxes-pretest": {"point_index": GEOM.point_index(0.04), "points_in_boxes_m": GEOM.in_boxes},
          "all-points": {}}[mode]
    args = (T, obs, n_obs, GEOM.model_points_m, depth_m, K, 0.04)
    kernel = fit_scores(*args, **kw)
    numpy = fit_scores(*args, **kw, compiled=False)
    np.testing.assert_allclose(kernel[0], numpy[0], atol=1.5 / 256)           # at most one point at the edge
    np.testing.assert_allclose(kernel[1], numpy[1], atol=0.002)
    assert kernel[0][-1] == 0.0 and kernel[1][-1] == 0.0       # behind the camera, no observations
    assert kernel[0][:-1].max() > 0.5 and kernel[1][:-1].max() > 0.05         # the scores say something


def test_fit_scores_take_numpy_for_other_depth_types(fit_inputs):
    """float64 depth (or a view that is not contiguous) is scored in numpy: the kernel reads float32 only."""
    from pallet6d.runtime.fit import fit_scores

    T, obs, n_obs, depth_m, K = fit_inputs
    a = fit_scores(T, obs, n_obs, GEOM.model_points_m, depth_m.astype(np.float64), K, 0.04, EPAL.boxes_m)
    b = fit_scores(T, obs, n_obs, GEOM.model_points_m, depth_m, K, 0.04, EPAL.boxes_m, compiled=False)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, atol=0.002)


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("n_obs", [[257], [-1]])
def test_fit_scores_refuse_counts_beyond_the_rows(fit_inputs, compiled, n_obs):
    from pallet6d.runtime.fit import fit_scores

    T, obs, _, depth_m, K = fit_inputs
    with pytest.raises(ValueError, match="n_obs"):
        fit_scores(T[:1], obs[:1], np.array(n_obs), GEOM.model_points_m, depth_m, K, 0.04, compiled=compiled)


@needs_kernel
@pytest.mark.parametrize("case", ["registered", "other frame", "shifted", "holes and noise", "near the border"])
def test_registration_counts_in_the_kernel_equal_numpy(case):
    """The registration test's scores and pair counts, compiled and in numpy, on simulated frames: exactly equal."""
    from pallet6d.runtime.registration import registration_score

    frame = sim_generate.generate_frame(get_preset("virtual-occluded"), seed=2)
    other = sim_generate.generate_frame(get_preset("virtual-occluded"), seed=3)
    depth = frame.depth_m.astype(np.float32)
    boxes = np.array([[x, y, x + w, y + h] for x, y, w, h in (g.bbox_visib_xywh for g in frame.pallets
                                                             if g.bbox_visib_xywh is not None)], float)
    rng = np.random.default_rng(0)
    if case == "other frame":
        depth = other.depth_m.astype(np.float32)
    elif case == "shifted":
        depth = np.roll(depth, 24, axis=1)
    elif case == "holes and noise":
        depth = depth + rng.normal(0, 0.02, depth.shape).astype(np.float32)
        depth[rng.uniform(size=depth.shape) < 0.2] = 0.0
    elif case == "near the border":
        boxes = np.array([[0.0, 0.0, 60.0, 40.0], [depth.shape[1] - 50.0, depth.shape[0] - 30.0, depth.shape[1],
                                                   depth.shape[0]]])
    kernel = registration_score(depth, frame.rgb, boxes)
    numpy = registration_score(depth, frame.rgb, boxes, compiled=False)
    assert kernel == numpy or (dataclasses.astuple(kernel)[2:] == dataclasses.astuple(numpy)[2:]
                               and np.allclose(dataclasses.astuple(kernel)[:2], dataclasses.astuple(numpy)[:2],
                                               equal_nan=True, rtol=0, atol=1e-12))
    assert case == "near the border" or kernel.judged


@needs_kernel
def test_ray_scores_in_the_kernel_equal_numpy():
    """The levelled search's ray scores, compiled (on one thread and on several) and in numpy: equal for poses that
    hit, graze and miss the points, and for points on the model's boards, in its openings and beyond it."""
    from pallet6d.runtime.level import ray_scores

    rng = np.random.default_rng(3)
    T_true = make_T(quat_to_rot([0.5, -0.5, 0.5, -0.5]), [0.1, 0.2, 3.0])        # pallet x across the view
    pts_pallet = EPAL.surface_points(300, seed=1)
    pts = pts_pallet @ T_true[:3, :3].T + T_true[:3, 3]
    pts = np.concatenate([pts, pts[:50] + [0.0, 0.0, 0.3], rng.uniform([-1, -1, 2], [1, 1, 4], (50, 3))])
    poses = [T_true] + [T_true @ _turn(yaw, (dx, 0.0, 0.0)) for yaw, dx in ((30.0, 0.0), (90.0, 0.1), (0.0, 0.4))]
    poses.append(make_T(np.eye(3), [5.0, 0.0, 3.0]))                                 # the rays miss it
    T = np.stack(poses)
    for window_m in (0.02, 0.05, 0.2):
        kernel = ray_scores(T, pts, EPAL.boxes_m, window_m)
        numpy = ray_scores(T, pts, EPAL.boxes_m, window_m, compiled=False)
        np.testing.assert_array_equal(kernel, numpy)
    many = np.concatenate([T] * 7)                                # 35 poses: several chunks of 8 for the threads
    np.testing.assert_array_equal(ray_scores(many, pts, EPAL.boxes_m, 0.05, threads=3),
                                  ray_scores(many, pts, EPAL.boxes_m, 0.05, compiled=False))
    assert kernel[0] == kernel.max() and kernel[-1] == 0.0
    assert ray_scores(T, np.zeros((0, 3)), EPAL.boxes_m, 0.05).tolist() == [0.0] * len(T)
    for window_m in (0.02, 0.05):                                  # the soft score: sums in another order
        np.testing.assert_allclose(ray_scores(many, pts, EPAL.boxes_m, window_m, threads=2, soft=True),
                                   ray_scores(many, pts, EPAL.boxes_m, window_m, compiled=False, soft=True),
                                   rtol=0, atol=1e-12)


@needs_kernel
def test_the_rays_try_the_nearest_boxes_first_with_the_same_hits():
    """The kernels stop at the first box that cannot be met before their nearest hit: random overlapping boxes, a
    camera inside one of them, rays that miss, the same hits as trying every box (numpy)."""
    from pallet6d.runtime.structure import cast_rays_boxes

    rng = np.random.default_rng(8)
    lo = rng.uniform(-1.0, 1.0, (40, 3))
    boxes = np.stack([lo, lo + rng.uniform(0.01, 0.6, (40, 3))], axis=1)
    inside = boxes[0].mean(0)
    for origin in (np.array([0.0, 0.0, -4.0]), inside):                     # the camera outside, then inside a box
        dirs = rng.uniform(-2.0, 2.0, (1, 500, 3)) - origin                  # s = 1 at these points
        hits, _ = kernels.cast_rays(origin[None], dirs, boxes, np.array([0]), np.array([40]))
        s, _ = cast_rays_boxes(origin[None], dirs, boxes)
        np.testing.assert_allclose(hits, s, rtol=1e-12, atol=0)
        if origin is inside:
            assert np.all(hits == 0.0)                                       # every ray starts in a box
        else:
            assert np.isinf(hits).any() and np.isfinite(hits).any() and (hits > 0).all()
    with pytest.raises(ValueError, match="at most"):
        kernels.along_rays(make_T(np.eye(3), [0.0, 0.0, 4.0])[None], np.ones((1, 5, 3)), np.array([5]),
                           np.zeros((kernels.MAX_BOXES + 1, 2, 3)), 0.1)


def test_the_soft_ray_score_peaks_at_the_true_pose_where_the_plain_one_is_flat():
    from pallet6d.runtime.level import ray_scores
    from pallet6d.runtime.structure import cast_rays_boxes

    T_true = make_T(quat_to_rot([0.5, -0.5, 0.5, -0.5]), [0.1, 0.2, 3.0])
    pts = EPAL.surface_points(1500, seed=5) @ T_true[:3, :3].T + T_true[:3, 3]
    R_pc = T_true[:3, :3].T
    s, _ = cast_rays_boxes((-R_pc @ T_true[:3, 3])[None], (pts @ R_pc.T)[None], EPAL.boxes_m)
    pts = pts[np.abs(s[0] - 1.0) < 1e-9]                                          # the camera sees these
    near = np.stack([T_true] + [T_true @ _turn(yaw, (dx, dy, 0.0))
                                for yaw, dx, dy in ((0.0, 0.0, 0.01), (0.0, 0.0, -0.01), (0.5, 0.0, 0.0))])
    for compiled in (True, False):
        if compiled and not kernels.available():
            continue
        plain = ray_scores(near, pts, EPAL.boxes_m, 0.05, compiled=compiled)
        soft = ray_scores(near, pts, EPAL.boxes_m, 0.05, compiled=compiled, soft=True)
        assert soft[0] == pytest.approx(plain[0]) == pytest.approx(1.0)            # every residual 0: both agree
        assert np.all(soft[1:] < soft[0] - 1e-3)               # a centimetre nearer or farther scores lower
        assert np.ptp(plain[:3]) <= 0.02                                         # the plain score barely tells


@needs_kernel
def test_a_kernel_built_from_another_version_is_refused(monkeypatch, caplog):
    """A stale in-place build with other signatures is never called: the numpy paths run instead."""
    kernels._functions.cache_clear()
    monkeypatch.setattr(kernels, "ABI", kernels.ABI + 1)
    try:
        with caplog.at_level(logging.WARNING, logger="pallet6d.runtime.kernels"):
            assert not kernels.available()
        assert "another version of kernels.c" in caplog.text
    finally:
        monkeypatch.undo()
        kernels._functions.cache_clear()
    assert kernels.available()


@needs_kernel
def test_the_move_along_the_rays_in_the_kernel_equals_numpy():
    """The points within the window along their viewing rays (`kernels.along_rays`: how many, their median residual,
    their summed directions) and the levelled refinement's move built on them, compiled and in numpy: the same up
    to rounding; the rows past each pose's count are left out."""
    from pallet6d.runtime.level import _along_rays, _along_rays_numpy

    rng = np.random.default_rng(4)
    T_true = make_T(quat_to_rot([0.5, -0.5, 0.5, -0.5]), [0.1, 0.2, 3.0])
    T = np.stack([T_true, T_true @ _turn(20.0, (0.05, 0.02, 0.0)), T_true @ _turn(0.0, (0.0, 0.0, 0.3))])
    surface = EPAL.surface_points(400, seed=2) @ T_true[:3, :3].T + T_true[:3, 3]
    pts = np.zeros((3, 450, 3))
    n_pts = np.array([450, 400, 120])
    pts[0] = np.concatenate([surface, rng.uniform([-1, -1, 2], [1, 1, 4], (50, 3))])
    pts[1, :400] = surface + rng.normal(0.0, 0.02, surface.shape)
    pts[2, :400] = surface                                          # past its count of 120: must not count
    count, shift_m, ray = kernels.along_rays(T, pts, n_pts, EPAL.boxes_m, 0.2, threads=2)
    want = _along_rays_numpy(T, pts, n_pts, EPAL.boxes_m, 0.2)
    np.testing.assert_array_equal(count, want[0])
    np.testing.assert_allclose(shift_m, want[1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(ray, want[2], rtol=1e-12, atol=1e-12)
    assert count[0] < 450 and count[2] == 0           # the far points, and a pose 30 cm off, are outside the window
    seen = kernels.along_rays(T_true[None], pts[2:3], n_pts[2:], EPAL.boxes_m, 0.2)[0]
    assert 0 < seen[0] <= 120                                                     # the rows past the count are not
    T_vc = make_T(np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float), [0.0, 0.0, 0.5])
    for on_floor in (np.zeros(3, bool), np.array([True, False, True])):
        kernel = _along_rays(T, pts, n_pts, EPAL.boxes_m, 0.2, T_vc, on_floor)
        numpy = _along_rays(T, pts, n_pts, EPAL.boxes_m, 0.2, T_vc, on_floor, compiled=False)
        np.testing.assert_allclose(kernel, numpy, rtol=0, atol=1e-12)
    assert not np.allclose(kernel[1], T[1])                                       # the noisy pose did move
    none = kernels.along_rays(T, pts, np.zeros(3, np.int64), EPAL.boxes_m, 0.2)
    assert none[0].tolist() == [0, 0, 0] and none[1].tolist() == [0.0] * 3 and not none[2].any()


@needs_kernel
def test_the_structure_checks_rays_in_the_kernel_equal_numpy():
    """`cast_rays` gives `cast_rays_boxes`' values exactly, for poses each with its own boxes: random overlapping
    boxes, rays from outside and from inside a box, rays along the axes (zero components), rays that miss."""
    from pallet6d.runtime.structure import cast_rays_boxes

    rng = np.random.default_rng(21)
    sets = []
    for k in (1, 7, 40):
        lo = rng.uniform(-1.0, 1.0, (k, 3))
        sets.append(np.stack([lo, lo + rng.uniform(0.01, 0.6, (k, 3))], axis=1))
    which = np.array([2, 0, 1, 2, 1])
    origin = np.stack([[0.0, 0.0, -4.0], [3.0, 0.5, 0.2], [0.1, -3.0, 0.0], sets[2][0].mean(0), [0.0, 0.0, 5.0]])
    dirs = rng.uniform(-1.0, 1.0, (5, 300, 3)) - origin[:, None] * 0.25
    dirs[:, :30] = np.eye(3)[rng.integers(0, 3, (5, 30))] * rng.choice([-1.0, 1.0], (5, 30, 1))   # along an axis
    from pallet6d.runtime.structure import BoxSets

    laid = BoxSets(sets)
    t_box, t_bbox = kernels.cast_rays(origin, dirs, laid.flat, laid.start[which], laid.count[which])
    for i, j in enumerate(which):
        want_box, want_bbox = cast_rays_boxes(origin[i:i + 1], dirs[i:i + 1], sets[j])
        np.testing.assert_array_equal(t_box[i], want_box[0])
        np.testing.assert_array_equal(t_bbox[i], want_bbox[0])
    assert np.isinf(t_box).any() and np.isfinite(t_box).any() and np.all(t_box[3] == 0.0)   # pose 3 starts inside
    assert np.all((t_bbox <= t_box) | np.isinf(t_box))
    many = np.zeros((kernels.MAX_BOXES + 1, 2, 3))
    with pytest.raises(ValueError, match="1 to 256 boxes"):
        kernels.cast_rays(origin, dirs, many, np.zeros(5, int), np.full(5, kernels.MAX_BOXES + 1))
    with pytest.raises(ValueError, match=f"within the {len(laid.flat)} given"):   # a set past the boxes' end
        kernels.cast_rays(origin, dirs, laid.flat, laid.start[which] + 1, laid.count[which])
    with pytest.raises(ValueError, match="dirs"):
        kernels.cast_rays(origin, dirs[:4], laid.flat, laid.start[which], laid.count[which])
