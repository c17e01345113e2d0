"""The Blender Cycles backend: a tiny scene rendered for real (small image, few samples)."""

from __future__ import annotations

import copy
import logging
import os
import shutil
import stat
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from psdfactory import PsdError
from psdfactory import config as psd_config
from psdfactory.io import read_json, read_png
from psdfactory.scene.render.cycles import DEFAULT_PYTHON, blender_python
from psdfactory.scene.stages import run_render

HAVE_BLENDER = bool(os.environ.get("PSD_BLENDER_PYTHON")) or DEFAULT_PYTHON.is_file()
needs_blender = pytest.mark.skipif(
    not HAVE_BLENDER and not os.environ.get("PSD_REQUIRE_BLENDER"),
    reason="no Blender environment (`make blender`); `make test` creates it and requires these tests",
)
slow = pytest.mark.slow


def cycles_config(cfg: dict, **cycles) -> dict:
    cfg = copy.deepcopy(cfg)
    cfg["render"]["backend"] = "cycles"
    cfg["render"]["cycles"].update({"samples": 4, **cycles})
    return psd_config.validate(cfg)


@pytest.fixture(scope="module")
def both(tiny_results, tmp_path_factory):
    """One tiny scene rendered by the fast backend (from the session fixture) and by Cycles."""
    cfg, root = tiny_results
    src = root / "tiny" / "scenes" / "tiny-000001"
    dst = tmp_path_factory.mktemp("cycles") / src.name
    shutil.copytree(src, dst)
    run_render(psd_config.render_params(cycles_config(cfg)), dst)
    return src, dst


@slow
@needs_blender
def test_cycles_writes_the_same_outputs_with_the_same_geometry(both):
    tiny, cyc = both
    img, mask = read_png(cyc / "image.png"), read_png(cyc / "mask.png")
    assert img.shape == (64, 64, 3) and img.dtype == np.uint8
    assert mask.shape == (64, 64) and mask.dtype == np.uint16
    mt, mc = read_json(tiny / "render.json"), read_json(cyc / "render.json")
    assert mc["backend"] == "cycles" and mc["cycles"]["device"].startswith(("CPU", "GPU"))
    assert mc["mm_per_px"] == mt["mm_per_px"] and mc["resolution"] == mt["resolution"]
    assert mc["look"]["light_dir"] == mt["look"]["light_dir"]  # the same drawn look
    # a real rendering: particles differ from the table, and the image is not flat
    assert img.std() > 5
    assert abs(float(img[mask > 0].mean()) - float(img[mask == 0].mean())) > 3


@slow
@needs_blender
def test_cycles_mask_ids_are_particle_ids_and_match_the_fast_backend(both):
    tiny, cyc = both
    n = read_json(cyc / "spec.json")["samplesize"]
    a, b = read_png(tiny / "mask.png").astype(int), read_png(cyc / "mask.png").astype(int)
    assert 0 <= b.min() and b.max() <= n  # only table (0) and particle ids + 1
    ids_a, ids_b = set(np.unique(a)) - {0}, set(np.unique(b)) - {0}
    assert len(ids_a ^ ids_b) <= 2  # the same particles are seen (a sliver may differ)
    # pixel by pixel: equal away from particle edges, nearly equal overall
    edges = ndimage.binary_dilation(ndimage.morphological_gradient(a, size=3) > 0)
    assert (a == b)[~edges].mean() > 0.995
    assert (a == b).mean() > 0.9


@slow
@needs_blender
def test_cycles_is_deterministic(both, tmp_path):
    _, cyc = both
    again = tmp_path / "again"
    shutil.copytree(cyc, again)
    cfg = psd_config.validate({"datasets": {"tiny": {"n_scenes": 1}}, "render": {"resolution": 64},
                               "train": {"datasets": ["tiny"]}})
    params = psd_config.render_params(cycles_config(cfg))
    run_render(params, again)
    np.testing.assert_array_equal(read_png(cyc / "mask.png"), read_png(again / "mask.png"))
    assert np.abs(read_png(cyc / "image.png").astype(int) - read_png(again / "image.png").astype(int)).max() <= 2


def test_the_blender_job_lies_beside_the_backend_and_no_host_module_imports_it():
    import psdfactory
    from psdfactory.scene.render import cycles

    assert cycles.SCRIPT.is_file() and cycles.SCRIPT.parent == Path(cycles.__file__).parent
    for f in Path(psdfactory.__file__).parent.rglob("*.py"):
        imports = [line for line in f.read_text().splitlines() if line.lstrip().startswith(("import ", "from "))]
        assert not any("blender_job" in line for line in imports), f


def test_missing_blender_environment_says_how_to_create_it(monkeypatch, tmp_path):
    monkeypatch.setenv("PSD_BLENDER_PYTHON", str(tmp_path / "nope" / "python"))
    with pytest.raises(PsdError, match="make blender"):
        blender_python()


@slow
def test_blender_failure_is_reported_with_its_output(monkeypatch, tiny_results, tmp_path):
    cfg, root = tiny_results
    fake = tmp_path / "python"
    fake.write_text("#!/bin/sh\necho 'bpy exploded: out of GPU memory' >&2\nexit 3\n")
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("PSD_BLENDER_PYTHON", str(fake))
    dst = tmp_path / "scene"
    shutil.copytree(root / "tiny" / "scenes" / "tiny-000000", dst)
    with pytest.raises(PsdError, match=r"exit code 3(.|\n)*out of GPU memory"):
        run_render(psd_config.render_params(cycles_config(cfg)), dst)
    assert read_json(dst / "render.json")["backend"] == "tiny"  # the old outputs are untouched


def test_config_limits_particles_for_cycles():
    cfg = {"datasets": {"big": {"n_scenes": 1, "count": [100, 40000], "table_size": 2000}},
           "render": {"backend": "cycles"}, "train": {"datasets": ["big"]}}
    with pytest.raises(PsdError, match="32766"):
        psd_config.validate(cfg)


def test_cycles_settings_do_not_rerun_the_fast_backend():
    base = {"datasets": {"a": {"n_scenes": 1}}, "train": {"datasets": ["a"]}}
    a = psd_config.validate(copy.deepcopy(base))
    b = psd_config.validate({**copy.deepcopy(base), "render": {"cycles": {"samples": 64}}})
    assert psd_config.render_params(a) == psd_config.render_params(b)
    c = psd_config.validate({**copy.deepcopy(base), "render": {"backend": "cycles", "cycles": {"samples": 64}}})
    assert psd_config.render_params(c)["cycles"]["samples"] == 64


@slow
@needs_blender
def test_a_batch_of_cycles_renders_runs_one_scene_at_a_time(tiny_results, tmp_path, caplog):
    from psdfactory.scene.stages import run_scenes

    cfg, root = tiny_results
    dirs = []
    for i in range(2):
        d = tmp_path / f"tiny-{i:06d}"
        shutil.copytree(root / "tiny" / "scenes" / f"tiny-{i:06d}", d)
        dirs.append(d)
    params = psd_config.render_params(cycles_config(cfg))
    caplog.set_level(logging.INFO, logger="psdfactory")
    summary = run_scenes("render", params, dirs, skip_up_to_date=True, jobs=2)
    assert sorted(summary["ran"]) == [d.name for d in dirs]
    assert any("run one at a time" in m for m in caplog.messages)
    assert all(read_json(d / "render.json")["backend"] == "cycles" for d in dirs)
    assert run_scenes("render", params, dirs, skip_up_to_date=True)["ran"] == []  # now up to date
