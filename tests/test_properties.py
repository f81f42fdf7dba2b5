"""Property-based tests (hypothesis): over the estimator's inputs, the bundle manifest, the replay index and the
BOP files, nothing raises but the documented errors, and nothing malformed becomes a pose.

Example counts are bounded (`settings` below) so the suite stays fast; the seed is fixed (derandomize) so a
run is repeatable.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from pallet6d.runtime.cameras import CameraError, ReplaySource, ReplayWriter, open_source  # noqa: E402
from pallet6d.runtime.geometry import check_K  # noqa: E402
from pallet6d.runtime.inputs import MAX_IMAGE_PIXELS, check_rgbd  # noqa: E402

from camera_fixtures import box_frame  # noqa: E402

FAST = settings(max_examples=40, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

# ------------------------------------------------------------------------------------------- JSON mutation

json_leaf = st.one_of(st.none(), st.booleans(), st.integers(-2**40, 2**40),
                      st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12))
json_value = st.recursive(json_leaf, lambda kids: st.one_of(st.lists(kids, max_size=4),
                                                            st.dictionaries(st.text(max_size=6), kids, max_size=4)),
                          max_leaves=8)


def _paths(doc, prefix=()) -> list[tuple]:
    """Every key path into a JSON document (its containers and leaves)."""
    out = [prefix]
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out += _paths(v, prefix + (i,))
    return out


@st.composite
def mutated(draw, doc):
    """`doc` with one place replaced by an arbitrary JSON value, or deleted (a key or a list item)."""
    doc = json.loads(json.dumps(doc))
    paths = [p for p in _paths(doc) if p]
    path = draw(st.sampled_from(paths))
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    if draw(st.booleans()) and draw(st.booleans()):
        del parent[path[-1]]
    else:
        parent[path[-1]] = draw(json_value)
    return doc


# --------------------------------------------------------------------------------------------- K and inputs

finite = st.floats(-1e4, 1e4, allow_nan=False)
any_float = st.floats(allow_nan=True, allow_infinity=True)


@FAST
@given(st.lists(st.one_of(finite, any_float), min_size=9, max_size=9), st.integers(8, 4000), st.integers(8, 4000))
def test_check_K_refuses_arbitrary_matrices_or_returns_a_camera_matrix(values, h, w):
    K = np.array(values).reshape(3, 3)
    try:
        out = check_K(K, (h, w))
    except ValueError:
        return
    assert np.all(np.isfinite(out)) and np.allclose(out[2], [0, 0, 1]) and out[1, 0] == 0
    assert out[0, 0] > 0 and out[1, 1] > 0 and 0 <= out[0, 2] <= w and 0 <= out[1, 2] <= h


@FAST
@given(st.integers(8, 4000), st.integers(8, 4000), st.floats(0.01, 40), st.floats(0.3, 3), st.floats(-0.05, 0.05),
       st.floats(-0.3, 1.3), st.floats(-0.3, 1.3), st.sampled_from(["none", "row", "K10"]))
def test_check_K_accepts_exactly_the_plausible_cameras(h, w, f, aspect, skew, cx, cy, damage):
    side = max(h, w)
    fx, fy = f * side, f * side * aspect
    K = np.array([[fx, skew * fx, cx * w], [0, fy, cy * h], [0, 0, 1]])
    if damage == "row":
        K[2] = [0.01, 0, 1]
    elif damage == "K10":
        K[1, 0] = 0.5
    plausible = (damage == "none" and 0.1 <= f <= 20 and 0.1 <= f * aspect <= 20 and 0.5 <= aspect <= 2
                 and abs(skew) <= 0.01 and 0 <= cx <= 1 and 0 <= cy <= 1)
    try:
        check_K(K, (h, w))
        accepted = True
    except ValueError:
        accepted = False
    assert accepted == plausible


def _valid_K(h, w, f=1.0):
    """A camera matrix for an (h, w) image whose focal length is `f` times its larger side."""
    return np.array([[f * max(h, w), 0, w / 2], [0, f * max(h, w), h / 2], [0, 0, 1]])


@st.composite
def frame_inputs(draw):
    """(rgb, depth, K, depth_scale, defect): a small frame, maybe with one defect named by `defect`."""
    h, w = draw(st.integers(8, 48)), draw(st.integers(8, 64))
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    depth_kind = draw(st.sampled_from(["uint16", ">u2", "float32", "float64"]))
    if depth_kind in ("uint16", ">u2"):
        depth = rng.integers(0, 6000, (h, w)).astype(depth_kind)
        scale = draw(st.sampled_from([None, 0.001, 0.0001]))
    else:
        depth = rng.uniform(0, 6, (h, w)).astype(depth_kind)
        scale = None
    K = _valid_K(h, w, draw(st.floats(0.3, 5)))
    defect = draw(st.sampled_from([None, None, "rgb_dtype", "rgb_shape", "depth_shape", "depth_dtype", "nan",
                                   "negative", "all_zero", "K_transposed", "K_nan", "K_huge", "K_shape",
                                   "K_outside", "scale"]))
    if defect == "rgb_dtype":
        rgb = rgb.astype(draw(st.sampled_from([np.float32, np.uint16, np.int8])))
    elif defect == "rgb_shape":
        rgb = rgb[..., :draw(st.sampled_from([1, 2]))]
    elif defect == "depth_shape":
        depth = depth[: h - 1] if draw(st.booleans()) else depth[..., None]
    elif defect == "depth_dtype":
        depth = depth.astype(draw(st.sampled_from([np.int32, np.uint8, np.complex64, np.bool_])))
    elif defect == "nan":
        depth = depth.astype(np.float32)
        depth[0, 0] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
        scale = None
    elif defect == "negative":
        depth = depth.astype(np.float32)
        depth[0, 0] = -1.0
        scale = None
    elif defect == "all_zero":
        depth = np.zeros_like(depth)
    elif defect == "K_transposed":
        K = K.T
    elif defect == "K_nan":
        K[draw(st.integers(0, 2)), draw(st.integers(0, 2))] = np.nan
    elif defect == "K_huge":
        K[0, 0] = K[1, 1] = 1e9
    elif defect == "K_shape":
        K = K[:2]
    elif defect == "K_outside":
        K[0, 2] = -5.0
    elif defect == "scale":
        depth = depth.astype(np.uint16)
        scale = draw(st.sampled_from([0.0, -0.001, float("nan"), float("inf")]))
    return rgb, depth, K, scale, defect


@FAST
@given(frame_inputs())
def test_check_rgbd_refuses_every_defect_and_accepts_the_rest(inputs):
    rgb, depth, K, scale, defect = inputs
    if defect is None:
        _, depth_m, K_out = check_rgbd(rgb, depth, K, scale)
        assert depth_m.dtype == np.float32 and depth_m.shape == rgb.shape[:2] and np.all(np.isfinite(depth_m))
    else:
        with pytest.raises((ValueError, TypeError)):
            check_rgbd(rgb, depth, K, scale)


def test_big_endian_depth_reads_as_its_values():
    depth = np.arange(64, dtype=np.uint16).reshape(8, 8) + 1000
    rgb = np.zeros((8, 8, 3), np.uint8)
    a = check_rgbd(rgb, depth, _valid_K(8, 8))[1]
    b = check_rgbd(rgb, depth.astype(">u2"), _valid_K(8, 8))[1]
    assert np.array_equal(a, b)


def test_an_image_over_the_size_limit_is_refused_before_any_work():
    h, w = 2200, MAX_IMAGE_PIXELS // 2200 + 8
    rgb = np.zeros((h, w, 3), np.uint8)
    with pytest.raises(ValueError, match="too large"):
        check_rgbd(rgb, np.ones((h, w), np.uint16), _valid_K(h, w))


@pytest.fixture(scope="module")
def estimator(bundle_dir):
    from pallet6d.runtime.estimator import PalletEstimator
    return PalletEstimator.from_bundle(bundle_dir, threads=1, score_threshold=0.0, min_fit=0.0, refine=False)


@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(frame_inputs())
def test_predict_raises_only_documented_errors_and_never_poses_a_defective_frame(estimator, inputs):
    rgb, depth, K, scale, defect = inputs
    if defect is not None:
        with pytest.raises((ValueError, TypeError)):
            estimator.predict(rgb, depth, K, scale)
        return
    for pose in estimator.predict(rgb, depth, K, scale):
        T = pose.T_cam_pallet
        assert np.all(np.isfinite(T)) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4)


def test_nonfinite_depth_is_checked_when_the_options_are_made():
    from pallet6d.runtime.estimator import EstimatorOptions
    with pytest.raises(ValueError, match="nonfinite_depth"):
        EstimatorOptions(nonfinite_depth="bogus")


# ---------------------------------------------------------------------------------------- the bundle manifest

@pytest.fixture(scope="module")
def manifest_doc(bundle_dir):
    return json.loads((Path(bundle_dir) / "manifest.json").read_text())


@FAST
@given(data=st.data())
def test_a_damaged_manifest_raises_only_bundle_error(bundle_dir, manifest_doc, tmp_path_factory, data):
    from pallet6d.runtime.bundle import BundleError, load_bundle

    doc = data.draw(mutated(manifest_doc))
    root = tmp_path_factory.mktemp("bundle")
    for p in Path(bundle_dir).iterdir():
        if p.name != "manifest.json":
            (root / p.name).symlink_to(p)
    (root / "manifest.json").write_text(json.dumps(doc))
    try:
        load_bundle(root)
    except BundleError:
        pass


# --------------------------------------------------------------------------------------------- replay index

@pytest.fixture(scope="module")
def replay_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("replay") / "rec"
    with ReplayWriter(out) as w:
        for i in range(3):
            w.write(box_frame(i))
    return out


def _play(root: Path, on_error: str) -> tuple[list, int]:
    """(frames, errors) of a whole replay; only CameraError may escape."""
    frames, errors = [], 0
    with ReplaySource(root, on_error=on_error) as src:
        for _ in range(50):
            try:
                f = src.read()
            except CameraError as exc:
                assert getattr(exc, "frame_number", None) is not None, exc
                errors += 1
                continue
            if f is None:
                break
            frames.append(f)
        else:
            raise AssertionError("the replay did not end")
    return frames, errors


@FAST
@given(data=st.data())
def test_a_damaged_replay_index_gives_camera_errors_or_valid_frames(replay_dir, tmp_path_factory, data):
    doc = json.loads((replay_dir / "camera.json").read_text())
    doc = data.draw(st.one_of(mutated(doc), json_value))
    root = tmp_path_factory.mktemp("rec")
    for sub in ("rgb", "depth"):
        (root / sub).symlink_to(replay_dir / sub)
    (root / "camera.json").write_text(json.dumps(doc))
    on_error = data.draw(st.sampled_from(["raise", "skip"]))
    try:
        frames, errors = _play(root, on_error)
    except CameraError:
        return   # the index as a whole is unusable: one clear error at start
    assert len(frames) + errors <= len(doc["frames"])
    for f in frames:
        assert f.rgb.shape == (60, 80, 3) and np.isfinite(f.timestamp_s)


# ------------------------------------------------------------------------------------------------ BOP files

@pytest.fixture(scope="module")
def bop_scene(sim_bop_dataset):
    scene = next(p for p in (Path(sim_bop_dataset) / "train").iterdir() if p.is_dir())
    return Path(sim_bop_dataset), scene.name


@FAST
@given(data=st.data())
def test_damaged_bop_files_give_camera_errors_or_valid_frames(bop_scene, tmp_path_factory, data):
    from pallet6d.runtime.evaluation import ground_truths_from_bop

    src_root, scene = bop_scene
    which = data.draw(st.sampled_from(["scene_camera.json", "scene_gt.json", "scene_gt_info.json"]))
    root = tmp_path_factory.mktemp("bop")
    shutil.copytree(src_root / "models", root / "models")
    dst = root / "train" / scene
    dst.mkdir(parents=True)
    for p in (src_root / "train" / scene).iterdir():
        if p.name.endswith(".json"):
            shutil.copy(p, dst / p.name)
        else:
            (dst / p.name).symlink_to(p)
    doc = json.loads((dst / which).read_text())
    (dst / which).write_text(json.dumps(data.draw(st.one_of(mutated(doc), json_value))))
    try:
        with open_source(f"bop:{root}", on_error="raise") as src:
            for _ in range(10):
                try:
                    f = src.read()
                except CameraError as exc:
                    assert exc.frame_number is not None, exc
                    continue
                if f is None:
                    break
                assert np.isfinite(f.K).all()
                ground_truths_from_bop(src.last_gts, f.rgb.shape[:2])
    except CameraError:
        return
