#!/usr/bin/env python
"""A copy of a results folder's datasets at a smaller image size, for training elsewhere.

A GPU node that should train on scenes made here may take only so many bytes (a copy over a
slow link, a size-limited transfer): 1,000 paper-size scenes are ~0.5 GB of 512-px images and
masks, and their particle manifests ~60 MB. The CNNs read every image resized to their input
size (224 or 299 px) anyway, so this writes what they read and nothing more:

- each image resized (area-averaged, as `learn.data.to_input` does) to --size px, as PNG or, with
  --jpeg QUALITY, as JPEG (4:4:4; lossy: say so wherever a figure trained on it is quoted);
- each mask resized by nearest neighbour (mask ids are labels) to the same size, as 16-bit PNG;
- the scene manifests with `image_path` (its suffix), `resolution` and `mm_per_px` rewritten to
  match (a particle's size in pixels stays size_mm / mm_per_px), every label unchanged;
- the particle manifests with the columns the training and evaluation read (`--particle-columns`),
  sizes as float32;
- with --no-masks, neither masks nor particle manifests (`mask_path` then names no file): what a
  CNN regressor without the dense size task (`train.size_cells: 0`) reads is the images and the
  scene manifests alone.

The instance estimator should not be trained on such a copy: it reads grains at their own
scale, which the resize changes: copy its datasets at their own size (--size = their resolution)
for that. Scenes are read from the manifests (their splits as they are); --splits keeps only some,
--per-split N the first N of each (a small set for a smoke test).

    .venv/bin/python bench/shrink_results.py --results results_paper_cpu --datasets train train_cycles \\
        --size 299 --jpeg 92 --out .carry/results_paper_cpu
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from psdfactory.manifest import PARTICLE_READ_COLUMNS


def shrink_image(rgb: np.ndarray, size: int) -> np.ndarray:
    from psdfactory.learn.data import to_input

    return to_input(rgb, size).permute(1, 2, 0).numpy()


def shrink_dataset(results: Path, dataset: str, out: Path, size: int, jpeg: int | None,
                   splits: tuple[str, ...] | None, particle_columns: tuple[str, ...] | None,
                   per_split: int | None = None) -> tuple[int, int]:
    """Writes `out/<dataset>/...` (masks and particles only with `particle_columns`); returns
    (scenes, bytes written)."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq
    from PIL import Image

    from psdfactory.io import atomic_path, read_png, write_parquet, write_png
    from psdfactory.learn.instances.draw import resize_mask
    from psdfactory.manifest import read_scenes

    scenes = read_scenes(results, dataset)
    if splits:
        scenes = scenes.filter(pc.is_in(scenes.column("split"), pa.array(list(splits))))
    rows = scenes.sort_by("index").to_pylist()
    if per_split is not None:
        kept: dict[str, list[dict]] = {}
        for r in rows:
            kept.setdefault(r["split"], []).append(r)
        rows = [r for split_rows in kept.values() for r in split_rows[:per_split]]
    suffix = ".jpg" if jpeg else ".png"
    written, t0 = 0, time.monotonic()
    for i, r in enumerate(rows):
        rgb = read_png(results / r["image_path"])
        if rgb.shape[0] != rgb.shape[1]:
            raise SystemExit(f"{r['image_path']}: {rgb.shape[1]} x {rgb.shape[0]} px; the factory's images are square")
        img_rel = str(Path(r["image_path"]).with_suffix(suffix))
        dst = out / img_rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        small = shrink_image(rgb, size)
        if jpeg:
            with atomic_path(dst) as tmp:
                Image.fromarray(small).save(tmp, format="JPEG", quality=jpeg, subsampling=0)
        else:
            write_png(dst, small, compress_level=9)
        written += dst.stat().st_size
        if particle_columns is not None:
            mask = read_png(results / r["mask_path"])
            write_png(out / r["mask_path"], resize_mask(mask, (size, size)).astype(np.uint16), compress_level=9)
            written += (out / r["mask_path"]).stat().st_size
        factor = rgb.shape[1] / size
        r.update(image_path=img_rel, resolution=size, mm_per_px=float(r["mm_per_px"]) * factor)
        if (i + 1) % 100 == 0 or i + 1 == len(rows):
            rate = (i + 1) / (time.monotonic() - t0)
            print(f"  {dataset}: {i + 1}/{len(rows)} scenes, {written / 2**20:.1f} MiB, {rate:.1f} scenes/s, "
                  f"ETA {(len(rows) - i - 1) / rate:.0f} s", flush=True)
    table = pa.Table.from_pylist(rows, schema=scenes.schema)
    spath = out / dataset / "manifest" / "scenes" / "shard-00000.parquet"
    write_parquet(spath, table)
    written += spath.stat().st_size
    if particle_columns is None:
        return len(rows), written
    keep = set(table.column("scene_id").to_pylist())
    parts = pq.read_table(results / dataset / "manifest" / "particles", columns=["scene_id", *particle_columns])
    parts = parts.filter(pc.is_in(parts.column("scene_id"), pa.array(sorted(keep))))
    parts = parts.cast(pa.schema([pa.field(f.name, pa.float32()) if pa.types.is_floating(f.type) else f
                                  for f in parts.schema]))
    ppath = out / dataset / "manifest" / "particles" / "shard-00000.parquet"
    ppath.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(parts, ppath, compression="zstd", compression_level=19)
    written += ppath.stat().st_size
    return len(rows), written


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results", required=True, help="the results folder holding the datasets")
    ap.add_argument("--datasets", nargs="+", required=True, help="the datasets to copy")
    ap.add_argument("--out", required=True, help="the new results folder (datasets under it as in --results)")
    ap.add_argument("--size", type=int, required=True, help="image and mask size in px (e.g. 299: InceptionV3's)")
    ap.add_argument("--jpeg", type=int, metavar="QUALITY", help="write images as JPEG of this quality (else PNG)")
    ap.add_argument("--splits", nargs="+", help="only these splits (default: all)")
    ap.add_argument("--particle-columns", nargs="+", default=list(PARTICLE_READ_COLUMNS),
                    help="particle manifest columns kept (default: %(default)s)")
    ap.add_argument("--per-split", type=int, metavar="N", help="only the first N scenes of each split")
    ap.add_argument("--no-masks", action="store_true", help="copy neither masks nor particle manifests")
    a = ap.parse_args()
    if a.size < 1:
        ap.error("--size takes a side in px of at least 1")
    if a.per_split is not None and a.per_split < 1:
        ap.error("--per-split takes a count of at least 1")
    if a.jpeg is not None and not 1 <= a.jpeg <= 100:
        ap.error("--jpeg takes a quality from 1 to 100")
    results, out = Path(a.results), Path(a.out)
    if out.resolve() == results.resolve():
        ap.error("--out must differ from --results")
    total = 0
    for ds in a.datasets:
        n, b = shrink_dataset(results, ds, out, a.size, a.jpeg, tuple(a.splits) if a.splits else None,
                              None if a.no_masks else tuple(a.particle_columns), a.per_split)
        total += b
        print(f"{ds}: {n} scenes, {b / 2**20:.1f} MiB", flush=True)
    print(f"written under {out}: {total / 2**20:.1f} MiB", flush=True)


if __name__ == "__main__":
    main()
