"""Contact sheet: a few scenes with their masks and labels, to look at before training."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .io import pyplot, read_png, save_figure
from .manifest import read_scenes


def colorize_mask(mask: np.ndarray) -> np.ndarray:
    """Instance ids → distinct colours (table black), stable per id."""
    ids = mask.astype(np.int64)
    rng = np.random.default_rng(12345)
    lut = rng.integers(60, 256, size=(int(ids.max()) + 1, 3)).astype(np.uint8)
    lut[0] = 0
    return lut[ids]


def contact_sheet(results_root: Path, dataset: str, out: Path, n: int = 6) -> Path:
    plt = pyplot()
    scenes = read_scenes(results_root, dataset).sort_by("index").slice(0, n).to_pylist()
    fig, axes = plt.subplots(len(scenes), 2, figsize=(6.4, 3.2 * len(scenes)), squeeze=False)
    for row, sc in zip(axes, scenes):
        img = read_png(Path(results_root) / sc["image_path"])
        mask = read_png(Path(results_root) / sc["mask_path"])
        row[0].imshow(img)
        row[1].imshow(colorize_mask(mask))
        row[0].set_title(
            f"{sc['scene_id']} ({sc['split']}), {sc['n_particles']} particles\n"
            f"number d10/50/90: {sc['d10_mm']:.1f}/{sc['d50_mm']:.1f}/{sc['d90_mm']:.1f} mm",
            fontsize=7,
        )
        row[1].set_title(
            f"mask: {sc['n_visible']} visible, {sc['mm_per_px']:.3f} mm/px\n"
            f"volume d10/50/90: {sc['d10_v_mm']:.1f}/{sc['d50_v_mm']:.1f}/{sc['d90_v_mm']:.1f} mm",
            fontsize=7,
        )
        for ax in row:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    save_figure(fig, out, dpi=110)
    return out
