"""Scene content: loads on every pallet type, pallet looks, distractors, truck beds, mixed scenes."""
import math
from dataclasses import replace

import numpy as np
import pytest

from pallet6d.runtime import geometry as g
from pallet6d.sim.loads import distractor_boxes, drum_boxes, load_boxes, pallet_look, truck_bed_boxes
from pallet6d.sim.pallets import PALLET_MODELS, get_pallet_model
from pallet6d.sim.presets import get_preset
from pallet6d.sim.scene import PalletPlacement
from pallet6d.sim.warehouse import build_scene


def _corners(box) -> np.ndarray:
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    return g.transform_points(box.T_world_box, signs * box.half_size_m)


@pytest.mark.parametrize("name", PALLET_MODELS)
def test_loads_stand_on_the_pallet_within_its_footprint(name):
    m = get_pallet_model(name)
    yaw = 0.7
    T = g.make_T(np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]),
                 [1.0, -2.0, m.size_m[2] / 2])
    p = PalletPlacement(1, name, T)
    for seed in range(12):    # every load kind comes up for every type
        boxes = load_boxes(np.random.default_rng(seed), p, clearance_m=1.5)
        assert boxes and all(b.instance_id == 0 for b in boxes)
        local = g.transform_points(g.invert_T(T), np.concatenate([_corners(b) for b in boxes]))
        assert local[:, 2].min() >= m.size_m[2] / 2 - 1e-6                  # on the top deck
        assert local[:, 2].max() <= m.size_m[2] / 2 + 1.45 + 1e-6           # under the clearance
        assert np.all(np.abs(local[:, :2]) <= m.size_m[:2] / 2 + 0.06)      # overhang of a few cm at most


@pytest.mark.parametrize("name", PALLET_MODELS)
def test_pallet_looks(name):
    m = get_pallet_model(name)
    rng = np.random.default_rng(0)
    for _ in range(20):
        base, parts, missing = pallet_look(rng, name, missing_board_prob=1.0)
        assert base.shape == (3,) and parts.shape == (len(m.boxes_m), 3)
        assert np.all((parts >= 0) & (parts <= 1))
        for k in missing:   # only an inner top deck board goes missing
            assert np.isclose(m.boxes_m[k, 1, 2], m.size_m[2] / 2)
    if m.material == "plastic" or len([b for b in m.boxes_m if np.isclose(b[1, 2], m.size_m[2] / 2)]) < 3:
        assert all(not pallet_look(rng, name, 1.0)[2] for _ in range(5))
    else:
        assert all(len(pallet_look(rng, name, 1.0)[2]) == 1 for _ in range(5))


def test_drum_is_a_regular_prism():
    boxes = drum_boxes((0.5, 0.5), 0.1, 0.3, 0.9, np.array([0.2, 0.3, 0.6]), 0)
    assert len(boxes) == 4
    pts = np.concatenate([_corners(b) for b in boxes])
    np.testing.assert_allclose(np.hypot(pts[:, 0] - 0.5, pts[:, 1] - 0.5), 0.3, atol=1e-9)   # corners on the circle
    np.testing.assert_allclose([pts[:, 2].min(), pts[:, 2].max()], [0.1, 1.0])
    # Filled: every point of the inscribed disc lies in some box.
    rng = np.random.default_rng(0)
    r, a = 0.3 * math.cos(math.pi / 8) * np.sqrt(rng.random(500)), rng.uniform(0, 2 * math.pi, 500)
    p = np.stack([0.5 + r * np.cos(a), 0.5 + r * np.sin(a), np.full(500, 0.5)], 1)
    inside = [np.all(np.abs(g.transform_points(g.invert_T(b.T_world_box), p)) <= b.half_size_m + 1e-9, 1)
              for b in boxes]
    assert np.all(np.any(inside, 0))
    with pytest.raises(ValueError, match="even"):
        drum_boxes((0, 0), 0, 0.3, 0.9, np.ones(3), 0, sides=5)


def test_distractors_and_truck_beds_stand_on_the_floor():
    rng = np.random.default_rng(1)
    for _ in range(30):
        boxes = distractor_boxes(rng, (2.0, 1.0), rng.uniform(-3, 3))
        z = np.concatenate([_corners(b) for b in boxes])[:, 2]
        assert boxes and abs(z.min()) < 1e-9
    bed = truck_bed_boxes(rng, (0.0, 1.2), 0.0, 8.0, 1.2)
    assert np.isclose(max(_corners(b)[:, 2].max() for b in bed), 1.2)


def test_mixed_scenes_mix_types_and_views():
    cfg = replace(get_preset("mixed").with_image_size(212, 120), appearance=None)
    rng = np.random.default_rng(5)
    types, vehicles = set(), 0
    for _ in range(8):
        scene = build_scene(cfg, rng)
        types |= {p.model_name for p in scene.pallets}
        vehicles += scene.vehicle is not None
    assert len(types) >= 5 and 0 < vehicles < 8


@pytest.mark.parametrize("kwargs, match", [
    (dict(layout="drone"), "layout"),
    (dict(view_probs=(0.5, 0.5, 0.5)), "view_probs"),
    (dict(approach_yaw_deg=90.0), "approach_yaw_deg"),
    (dict(missing_board_prob=1.5), "missing_board_prob"),
    (dict(pocket_obstacle_prob=-0.1), "pocket_obstacle_prob"),
    (dict(cam_height_m=(2.5, 0.1)), "cam_height_m"),
    (dict(sensor_mix=("d435", "kinect")), "sensor_mix"),
])
def test_bad_scene_configs_raise(kwargs, match):
    from pallet6d.sim.presets import SimConfig

    with pytest.raises(ValueError, match=match):
        SimConfig(name="t", width=160, height=80, hfov_deg=80.0, **kwargs)


def test_new_presets_cover_the_catalogue_and_the_paper_presets_do_not_change_shape():
    from pallet6d.sim.presets import PAPER_PRESETS, PRESETS

    for name in ("forklift-approach", "mixed"):
        cfg = PRESETS[name]
        assert set(cfg.pallet_models) == set(PALLET_MODELS) and cfg.rich_content and cfg.appearance is not None
    assert PRESETS["forklift-approach"].layout == "forklift" and PRESETS["forklift-approach"].sensor == "d435"
    for name in PAPER_PRESETS:
        cfg = PRESETS[name]
        assert cfg.pallet_models == ("epal",) and not cfg.rich_content and cfg.layout in ("warehouse", "indoor")
