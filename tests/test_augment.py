"""Augmentations that keep the labels true; the scale augmentation against a real re-render."""

import dataclasses

import numpy as np
import pytest
import torch

from psdfactory import config as psd_config
from psdfactory.io import read_json, read_png
from psdfactory.learn.augment import augment_d4, photometric, rescale, rescale_one
from psdfactory.learn.data import to_input
from psdfactory.scene.render import render_scene
from psdfactory.scene.render.look import RenderParams
from psdfactory.scene.stages import load_geometry, load_poses

from .conftest import make_scene, tiny_config


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def test_rescale_factor_is_the_one_the_crop_applies():
    img = torch.randint(0, 255, (3, 64, 64), dtype=torch.uint8, generator=_gen())
    out, f = rescale_one(img, 1.3, _gen())
    assert out.shape == img.shape and out.dtype == torch.uint8 and f == pytest.approx(64 / round(64 / 1.3))
    out, f = rescale_one(img, 0.8, _gen())
    assert out.shape == img.shape and f == pytest.approx(round(64 * 0.8) / 64)
    x = torch.randint(0, 255, (5, 3, 32, 32), dtype=torch.uint8, generator=_gen())
    y = torch.tensor([[1.0, 2.0, 3.0]] * 5)
    xa, ya = rescale(x, y, (0.8, 1.25), _gen(3))
    ratio = ya / y
    assert torch.allclose(ratio, ratio[:, :1].expand_as(ratio)) and (ratio.min() >= 0.78) and (ratio.max() <= 1.28)
    assert not torch.allclose(ratio, torch.ones_like(ratio))
    assert rescale(x, y, (1.0, 1.0), _gen())[0] is x  # off
    with pytest.raises(ValueError, match="1/2 < lo"):
        rescale(x, y, (0.4, 1.0), _gen())


def test_a_magnified_image_shows_the_scene_rendered_at_that_scale(tmp_path):
    """Magnify the middle of a render by s = 2 and compare with the same scene, every particle
    and position scaled by 2, rendered by the same camera: the masks agree, and the labels of the
    scaled scene are the magnified image's labels (s × the original's)."""
    cfg = tiny_config(n_scenes=1, count=[40, 50], table_size=60)
    d = make_scene(cfg, tmp_path / "tiny-000000")
    spec, geo = read_json(d / "spec.json"), load_geometry(d)
    pos, quat, _ = load_poses(d)
    s = 2.0
    big = dataclasses.replace(geo, vertices=geo.vertices * s, size_mm=geo.size_mm * s,
                              volume_mm3=geo.volume_mm3 * s**3, dims_mm=geo.dims_mm * s, sieve_mm=geo.sieve_mm * s)
    assert read_json(d / "labels.json")["size_definition"] == "sieve"  # the default: labels of the sieve size
    _, mask_big, _ = render_scene(spec, big, pos * s, quat, RenderParams.from_dict(psd_config.render_params(cfg)),
                                  spec["entropy"])
    mask = read_png(d / "mask.png")
    n = mask.shape[0]
    c = n // 2  # the middle half, magnified 2×, nearest neighbour (ids)
    zoom = np.kron(mask[c // 2 : c // 2 + c, c // 2 : c // 2 + c], np.ones((2, 2), dtype=mask.dtype))
    agree = (zoom == mask_big).mean()
    assert agree > 0.9, agree  # measured 0.946: particle edges differ by the pixel rounding
    labels = read_json(d / "labels.json")
    from psdfactory.psd import weighted_percentiles

    assert weighted_percentiles(big.sieve_mm, None) == pytest.approx(s * np.array(
        [labels["d10_mm"], labels["d50_mm"], labels["d90_mm"]]))
    # the augmentation, given the whole image and s = 2, crops a window of n/2 and doubles the labels
    x = to_input(read_png(d / "image.png"), None)[None]
    _, y2 = rescale(x, torch.tensor([[labels["d10_mm"], labels["d50_mm"], labels["d90_mm"]]]), (2.0, 2.0), _gen())
    assert y2[0].numpy() == pytest.approx(weighted_percentiles(big.sieve_mm, None), rel=1e-6)


def test_photometric_changes_colours_not_geometry():
    x = torch.zeros(4, 3, 32, 32, dtype=torch.uint8)
    x[:, :, 8:24, 8:24] = 200  # a bright square on a dark table
    out = photometric(x, _gen(1), 1.0)
    assert out.shape == x.shape and out.dtype == torch.uint8 and not torch.equal(out, x)
    inside, outside = out[:, :, 12:20, 12:20].float().mean(), out[:, :, :4, :4].float().mean()
    assert inside > outside + 50  # the square is still where it was, still brighter
    assert torch.equal(photometric(x, _gen(1), 0.0), x)
    assert torch.equal(photometric(x, _gen(5), 1.0), photometric(x, _gen(5), 1.0))  # reproducible


def test_d4_keeps_every_pixel():
    x = torch.arange(2 * 3 * 4 * 4, dtype=torch.uint8).view(2, 3, 4, 4)
    out = augment_d4(x, _gen())
    for i in range(2):
        assert sorted(out[i].flatten().tolist()) == sorted(x[i].flatten().tolist())


def test_noise_field_is_standardised_and_as_coarse_as_its_cell():
    from psdfactory.learn.augment import noise_field

    def corr_at(field, lag):  # correlation of the field with itself shifted by `lag` px
        a, b = field[:, :-lag].flatten(), field[:, lag:].flatten()
        return float(torch.corrcoef(torch.stack([a, b]))[0, 1])

    fine, coarse = noise_field((96, 128), 1.5, _gen(2)), noise_field((96, 128), 8.0, _gen(2))
    for f in (fine, coarse):
        assert f.shape == (96, 128) and abs(float(f.mean())) < 1e-4 and abs(float(f.std()) - 1) < 1e-3
    assert corr_at(coarse, 3) > 0.7 > 0.4 > corr_at(fine, 3)  # an 8-px cell is still alike 3 px on; 1.5 px not


def test_surface_texture_marks_the_grains_only():
    """Texture on the foreground of some images, the background untouched, reproducible, off at 0."""
    from psdfactory.learn.augment import surface_texture

    x = torch.full((8, 3, 48, 48), 40, dtype=torch.uint8)
    x[:, :, 8:40, 8:40] = 150  # a grain on a dark table
    fg = torch.zeros(8, 48, 48)
    fg[:, 8:40, 8:40] = 1.0
    out = surface_texture(x, fg, _gen(4), 1.0)
    assert out.shape == x.shape and out.dtype == torch.uint8
    assert torch.equal(out[:, :, :8], x[:, :, :8]) and torch.equal(out[:, :, :, 40:], x[:, :, :, 40:])  # background
    changed = [not torch.equal(out[i], x[i]) for i in range(8)]
    assert 0 < sum(changed) < 8  # on a share of the images (TEXTURE_SHARE), not all
    for i in (i for i in range(8) if changed[i]):
        grain = out[i, :, 8:40, 8:40].float()
        assert grain.std() > 3 and abs(float(grain.mean()) - 150) < 25  # textured, about as bright
    assert torch.equal(surface_texture(x, fg, _gen(4), 1.0), out)
    assert torch.equal(surface_texture(x, fg, _gen(4), 0.0), x)
    weak = surface_texture(x, fg, _gen(4), 0.3)  # a lower strength: the same images, less contrast
    assert weak[:, :, 8:40, 8:40].float().std() < out[:, :, 8:40, 8:40].float().std()


def test_grain_colour_gives_each_grain_a_colour_of_its_own():
    """Two touching grains on a table: where an image is recoloured each grain is one colour, the two
    differ, the table and the pixels' share of grain do not change; reproducible, off at 0."""
    from psdfactory.learn.augment import GRAIN_BRIGHTNESS, GRAIN_CAST, grain_colour, grain_regions
    from psdfactory.learn.instances.targets import instance_targets

    mask = np.zeros((48, 48), dtype=np.int64)
    mask[8:40, 8:24], mask[8:40, 24:40] = 1, 2  # two grains meeting along column 24
    fg, boundary, _ = instance_targets(mask)
    regions = grain_regions(torch.from_numpy(fg).float(), torch.from_numpy(boundary).float())
    assert set(np.unique(regions)) == {0, 1, 2}  # two grains and the table, the boundary given to its grain
    assert (regions[mask == 0] == 0).all() and len(np.unique(regions[mask == 1])) == 1
    assert len(np.unique(regions[mask == 2])) == 1 and regions[20, 10] != regions[20, 30]

    x = torch.full((8, 3, 48, 48), 40, dtype=torch.uint8)
    x[:, :, 8:40, 8:40] = 128
    fgs = torch.from_numpy(fg).float().expand(8, 48, 48)
    bds = torch.from_numpy(boundary).float().expand(8, 48, 48)
    out = grain_colour(x, fgs, bds, _gen(5), 1.0)
    assert out.shape == x.shape and out.dtype == torch.uint8
    assert torch.equal(out[:, :, :8], x[:, :, :8]) and torch.equal(out[:, :, :, 40:], x[:, :, :, 40:])  # table
    changed = [not torch.equal(out[i], x[i]) for i in range(8)]
    assert 0 < sum(changed) < 8  # a share of the images (GRAIN_COLOUR_SHARE)
    for i in (i for i in range(8) if changed[i]):
        left, right = out[i, :, 8:40, 8:24].float(), out[i, :, 8:40, 24:40].float()
        assert left.std(dim=(1, 2)).max() == 0 and right.std(dim=(1, 2)).max() == 0  # one colour a grain
        assert not torch.equal(left[:, 0, 0], right[:, 0, 0])  # a colour of its own
        assert (left[:, 0, 0] / 128).log().abs().max() <= GRAIN_CAST + GRAIN_BRIGHTNESS + 0.01  # within the ranges
    assert torch.equal(grain_colour(x, fgs, bds, _gen(5), 1.0), out)
    assert torch.equal(grain_colour(x, fgs, bds, _gen(5), 0.0), x)
