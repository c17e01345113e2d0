#!/usr/bin/env python
"""What the instance network sees in a photo: its four maps side by side with the photo.

Reads each photo as `psdfactory predict` does (the same scale, `--auto-scale` included, the same
tiling) and writes one PNG per photo: the photo at the scale the network read it, and the maps it
predicted there — foreground probability, boundary probability, normalised distance to the
boundary, and the size map (log size of each pixel's grain) — each as grey levels 0..1, cut to a
window of at most `--window` px so that grains stay visible. Use it when the overlay of `predict
--overlay` shows grains cut into pieces or gaps taken for grains: the maps say which of the
network's outputs goes wrong (a foreground map that takes the gaps for grains, a boundary map that
follows the grains' texture), which says what the training scenes lack.

    .venv/bin/python bench/photo_maps.py --model results/models/instances/model.pt \
        --mm-per-px 0.288 --auto-scale data/photos/real/barton_creek.jpg --out maps/
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

LABELS = ("photo", "foreground", "boundary", "distance", "size map")


def panel(image: np.ndarray, maps: np.ndarray, window: int) -> np.ndarray:
    """The photo (H×W×3 uint8, at the maps' size) and its maps (C×H×W in [0, 1]) as one uint8
    image: a 3-wide grid of labelled tiles cut to the top-left `window` px."""
    from PIL import Image, ImageDraw

    h, w = min(window, maps.shape[1]), min(window, maps.shape[2])
    tiles = [image[:h, :w]] + [np.repeat((np.clip(m[:h, :w], 0, 1) * 255).astype(np.uint8)[..., None], 3, axis=2)
                               for m in maps]
    cols = 3
    rows = -(-len(tiles) // cols)
    out = np.full((rows * h, cols * w, 3), 255, dtype=np.uint8)
    for k, t in enumerate(tiles):
        r, c = divmod(k, cols)
        out[r * h:(r + 1) * h, c * w:(c + 1) * w] = t
    im = Image.fromarray(out)
    draw = ImageDraw.Draw(im)
    for k, name in enumerate(LABELS[:len(tiles)]):
        r, c = divmod(k, cols)
        draw.rectangle([c * w, r * h, c * w + 8 * len(name) + 8, r * h + 16], fill=(0, 0, 0))
        draw.text((c * w + 4, r * h + 2), name, fill=(255, 255, 0))
    return np.asarray(im)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("photos", nargs="+", help="photo files")
    ap.add_argument("--model", required=True, help="an instance model's model.pt")
    from psdfactory.cli import mm_per_px_arg

    ap.add_argument("--mm-per-px", type=mm_per_px_arg, default=None, help="the photos' scale (as predict's)")
    ap.add_argument("--auto-scale", action=argparse.BooleanOptionalAction, default=None,
                    help="read them as predict --auto-scale / --no-auto-scale does (default: the model's own)")
    ap.add_argument("--window", type=int, default=600, help="px of the maps shown per side (default 600)")
    ap.add_argument("--out", default="photo_maps", help="folder for <photo stem>.png (default photo_maps/)")
    a = ap.parse_args(argv)
    if a.window < 32:
        ap.error(f"--window must be at least 32 px, got {a.window}")

    from PIL import Image

    from psdfactory import PsdError
    from psdfactory.deploy.predict import check_outputs, load_predictor, network_size, read_at_scale
    from psdfactory.io import read_photo, write_png

    try:
        check_outputs(Path(a.model), a.photos, other_dirs={"--out": Path(a.out)})  # refused before any work
        est = load_predictor(Path(a.model))
    except PsdError as e:
        ap.error(str(e))
    if not est.finds_grains:
        ap.error(f"{a.model} is not a model that finds grains (arch {est.meta.get('arch')!r}): it has no maps")
    if a.auto_scale is not None:
        est.auto_scale = a.auto_scale
    seen: dict = {}
    read = est.read

    def keep_maps(outputs, mm_per_px):
        seen["maps"] = outputs[0]
        return read(outputs, mm_per_px)

    est.read = keep_maps
    out = Path(a.out)
    failed = 0
    for p in map(Path, a.photos):
        try:
            image, size_hw = read_photo(p, need=lambda h, w, p=p: network_size(p, h, w, est.meta, a.mm_per_px))
            _, hw = read_at_scale(est, image, size_hw, a.mm_per_px, where=str(p))
        except PsdError as e:
            print(f"{p}: {e}", file=sys.stderr)
            failed += 1
            continue
        maps = seen["maps"]
        shown = np.asarray(Image.fromarray(image).resize((hw[1], hw[0]), Image.BILINEAR))
        write_png(out / f"{p.stem}.png", panel(shown, maps, a.window))
        fg = maps[0] > est.post["threshold"]
        print(f"{p}: read at {hw[1]}x{hw[0]} px; foreground {fg.mean():.0%} of the pixels; "
              f"wrote {out / (p.stem + '.png')}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
