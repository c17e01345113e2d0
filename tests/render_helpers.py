"""Rendering a scene of the tiny test dataset again with one render setting changed."""

from __future__ import annotations

import copy
import shutil
from pathlib import Path


def rerender(tiny_results: tuple[dict, Path], tmp_path: Path, section: str, probabilities=(0.0, 1.0)) -> dict:
    """Scene tiny-000001 rendered again with `render.<section>.probability` at each of
    `probabilities`, each in its own copy of the scene folder → {probability: folder}; the
    original folder is `tiny_results`' own, untouched."""
    from psdfactory import config as psd_config
    from psdfactory.scene.stages import run_render

    cfg, root = tiny_results
    src = root / "tiny" / "scenes" / "tiny-000001"
    dirs = {}
    for p in probabilities:
        d = tmp_path / f"p{p}"
        shutil.copytree(src, d)
        c = copy.deepcopy(cfg)
        c["render"][section] = {"probability": p}
        run_render(psd_config.render_params(psd_config.validate(c)), d)
        dirs[p] = d
    return dirs
