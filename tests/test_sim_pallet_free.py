import numpy as np
import pytest

from pallet6d.sim.pallet_free import without_pallets
from pallet6d.sim.scene import Box

H = 0.144                                               # a pallet's height


def _box(x, y, z_bottom, size, instance_id=0):
    T = np.eye(4)
    T[:3, 3] = [x, y, z_bottom + size[2] / 2]
    return Box(T, np.asarray(size, float) / 2, 0, (0.5, 0.5, 0.5), instance_id)


def _pallet(x, y, z_bottom, instance_id):
    """Three blocks and a deck: the parts of one pallet."""
    parts = [_box(x + dx, y, z_bottom, (0.1, 0.8, H - 0.022), instance_id) for dx in (-0.55, 0.0, 0.55)]
    return parts + [_box(x, y, z_bottom + H - 0.022, (1.2, 0.8, 0.022), instance_id)]


def _bottom(b):
    return b.T_world_box[2, 3] - b.half_size_m[2]


def test_a_load_on_a_floor_pallet_is_set_on_the_floor_with_the_carton_on_it():
    load = _box(0.0, 0.0, H, (1.0, 0.7, 0.5))
    top = _box(0.0, 0.0, H + 0.5, (0.4, 0.3, 0.3))
    wall = _box(0.0, 3.0, 0.0, (4.0, 0.1, 3.0))
    out = without_pallets(_pallet(0.0, 0.0, 0.0, 1) + [load, top, wall])
    assert len(out) == 3 and all(b.instance_id == 0 for b in out)
    assert [_bottom(b) for b in out] == pytest.approx([0.0, 0.5, 0.0])
    hanging = without_pallets(_pallet(0.0, 0.0, 0.0, 1) + [load, top, wall], set_down=False)
    assert [_bottom(b) for b in hanging] == pytest.approx([H, H + 0.5, 0.0])


def test_a_load_on_a_stack_falls_through_the_whole_stack_but_not_through_a_rack_beam():
    stack = _pallet(0.0, 0.0, 0.0, 1) + _pallet(0.0, 0.0, H, 2) + _pallet(0.0, 0.0, 2 * H, 3)
    on_stack = _box(0.0, 0.0, 3 * H, (1.0, 0.7, 0.4))
    beam = _box(3.0, 0.0, 1.4, (2.5, 0.1, 0.1))                 # a rack level at 1.5 m, a floor pallet under it
    rack = _pallet(3.0, 0.0, 1.5, 4) + _pallet(3.0, 0.0, 0.0, 5)
    on_rack = _box(3.0, 0.0, 1.5 + H, (1.0, 0.7, 0.4))
    out = without_pallets(stack + [on_stack, beam] + rack + [on_rack])
    assert [_bottom(b) for b in out] == pytest.approx([0.0, 1.4, 1.5])
    assert without_pallets([]) == [] and without_pallets([beam]) == [beam]


def test_a_pallet_free_dataset_draws_the_presets_scenes_without_pallets_or_ground_truth(tmp_path, monkeypatch):
    import pallet6d.sim.generate as generate
    from pallet6d.runtime.bop import BopDataset
    from pallet6d.sim.dataset import write_dataset
    from pallet6d.sim.pallet_free import generate_pallet_free_frame
    from pallet6d.sim.presets import get_preset

    scenes = []
    render = generate.render_with_sensors
    monkeypatch.setattr(generate, "render_with_sensors",
                        lambda config, scene, *a, **k: scenes.append(scene) or render(config, scene, *a, **k))
    config = get_preset("forklift-approach").with_image_size(320, 180)
    write_dataset(config, 2, 5, tmp_path / "d", pallet_free="set-down")
    ds = BopDataset(tmp_path / "d")
    assert len(ds) == 2 and all(ds[i].gts == [] for i in range(2))
    assert len(scenes) == 2 and all(b.instance_id == 0 for s in scenes for b in s.boxes)
    assert all(s.vehicle is not None for s in scenes)          # the forklift's own view, fork tips included
    frame = generate_pallet_free_frame(config, 5, 0, "set-down")
    np.testing.assert_array_equal(frame.rgb, ds[0].rgb)         # seeded frame by frame
    assert frame.pallets == [] and frame.faces == []
    with pytest.raises(ValueError, match="loads must be one of"):
        generate_pallet_free_frame(config, 5, 0, "floating")
