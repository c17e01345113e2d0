"""Contact sheet: a few scenes with their masks and labels, to look at before training."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import pyplot, read_png, save_figure
from ..manifest import read_scenes


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
    for row, sc in zip(axes, scenes, strict=True):
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


def mask_agreement(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Fraction of pixels with the same id: overall, and away from the edges of `a`'s regions
    (pixels within one pixel of an id change are where two renderers may disagree)."""
    from scipy import ndimage

    a, b = a.astype(np.int64), b.astype(np.int64)
    edges = ndimage.binary_dilation(ndimage.morphological_gradient(a, size=3) > 0)
    same = a == b
    return float(same.mean()), float(same[~edges].mean()) if (~edges).any() else 1.0


def compare_backends(results_root: Path, dataset: str, n: int, render_params: dict, out_dir: Path) -> dict:
    """Render the first `n` scenes of `dataset` with both backends from the same settled poses;
    write ``compare.png`` (images side by side, mask differences) and ``compare.json``."""
    import shutil
    import time

    from .. import PsdError
    from ..io import write_json
    from .render.cycles import blender_python
    from .stages import run_render

    try:
        blender_python()
    except PsdError as e:
        hint = "(or set show.compare_backends: 0 to leave the backend comparison out of the report)"
        raise PsdError(f"{e}\n{hint}") from None
    plt = pyplot()
    scenes = read_scenes(results_root, dataset).sort_by("index").slice(0, n).to_pylist()
    backends = ("tiny", "cycles")
    rows = []
    fig, axes = plt.subplots(len(scenes), 3, figsize=(9.6, 3.3 * len(scenes)), squeeze=False)
    for ax_row, sc in zip(axes, scenes, strict=True):
        src = (Path(results_root) / sc["image_path"]).parent
        out = {}
        for b in backends:
            d = Path(out_dir) / b / sc["scene_id"]
            d.mkdir(parents=True, exist_ok=True)
            for f in ("spec.json", "geometry.npz", "poses.parquet"):
                shutil.copyfile(src / f, d / f)
            t0 = time.perf_counter()
            run_render({**render_params, "backend": b}, d)
            out[b] = {"seconds": time.perf_counter() - t0, "image": read_png(d / "image.png"),
                      "mask": read_png(d / "mask.png")}
        agree, agree_inner = mask_agreement(out["tiny"]["mask"], out["cycles"]["mask"])
        rows.append({"scene_id": sc["scene_id"], "n_particles": sc["n_particles"],
                     **{f"seconds_{b}": round(out[b]["seconds"], 3) for b in backends},
                     "mask_agreement": agree, "mask_agreement_off_edges": agree_inner})
        for ax, b in zip(ax_row, backends, strict=False):  # (the third axis shows where the masks differ)
            ax.imshow(out[b]["image"])
            ax.set_title(f"{sc['scene_id']}: {b} ({out[b]['seconds']:.1f} s)", fontsize=8)
        diff = out["tiny"]["mask"] != out["cycles"]["mask"]
        faint = colorize_mask(out["tiny"]["mask"]) // 3
        ax_row[2].imshow(np.where(diff[..., None], [255, 40, 40], faint).astype(np.uint8))
        ax_row[2].set_title(f"masks differ (red): {100 * (1 - agree):.1f} % of pixels,\n"
                            f"{100 * (1 - agree_inner):.2f} % away from edges", fontsize=8)
        for ax in ax_row:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    save_figure(fig, Path(out_dir) / "compare.png", dpi=110)
    summary = {"dataset": dataset, "resolution": render_params["resolution"],
               "cycles": render_params.get("cycles", {}), "scenes": rows}
    write_json(Path(out_dir) / "compare.json", summary)
    return summary
