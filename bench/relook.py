#!/usr/bin/env python
"""The same scenes in another look: re-render a folder of scene folders with other render settings.

A model that reads one look well and another badly is reading the look, not the particles. This
script takes finished scenes (folders with spec.json, geometry.npz and poses.parquet: the
workflow's `results/<dataset>/scenes/*`, or bench/paper_look.py's) and renders each again with a
config's `render` block and any `--set render.KEY=VALUE` on top — the same particles and poses,
and the source's labels, so the same references — into --out/<scene>/, so that a model's readings
of the two looks can be compared scene by scene (bench/calibration_basis.py, bench/paper_look.py's
scoring). The labels say which particles are in view, so a render that frames another part of the
table (another `view_fraction`) is refused; resolution, colours, light and camera effects may change.

    .venv/bin/python bench/relook.py --scenes /tmp/psd-paper-look/scenes --out /tmp/relook/bright \\
        --config config/config.yaml --set render.resolution=1000 \\
        --set 'render.table_palette=[[0.86, 0.85, 0.83], [0.9, 0.89, 0.88]]'

A scene already rendered under --out is kept (delete it to render it again).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

COPIED = ("spec.json", "geometry.npz", "poses.parquet", "simulate.json", "particles.parquet", "labels.json")


def render_settings(config: Path, settings: list[str]) -> dict:
    """The render slice `config`'s own render block gives with `settings` (render.KEY=VALUE) applied, validated."""
    from psdfactory import config as C

    cfg = C.load_config(config, edit=lambda raw: C.apply_settings(raw, settings, ("render.",)))
    return C.render_params(cfg)


def view_mm(scene: Path) -> float:
    """The width of table a scene's render shows (mm), from its render.json."""
    from psdfactory import PsdError
    from psdfactory.io import read_json

    rend = read_json(scene / "render.json")
    try:
        return float(rend["mm_per_px"]) * int(rend["resolution"])
    except (KeyError, TypeError, ValueError):
        raise PsdError(f"{scene / 'render.json'}: no mm_per_px and resolution") from None


def check_same_view(src: Path, dst: Path) -> None:
    """Refuse a render of another part of the table than the source's (its labels would not be of it);
    the scene's new folder is removed."""
    from psdfactory import PsdError

    a, b = view_mm(src), view_mm(dst)
    if abs(a - b) > 1e-3 * a:
        shutil.rmtree(dst)
        raise PsdError(f"{dst.name}: the render shows {b:.1f} mm of table where the source shows {a:.1f} mm; the "
                       "labels are the source's, so keep its view (render.view_fraction) and change only how it looks")


def relook(scenes: list[Path], out: Path, params: dict) -> list[Path]:
    """Each scene rendered again with `params` into out/<scene name>/ (its other files copied)."""
    from psdfactory.scene.stages import run_render

    done, t0 = [], time.perf_counter()
    for i, src in enumerate(scenes, 1):
        dst = out / src.name
        dst.mkdir(parents=True, exist_ok=True)
        for name in COPIED:
            if (src / name).exists():
                shutil.copy2(src / name, dst / name)
        if not (dst / "image.png").exists():
            run_render(params, dst)
            check_same_view(src, dst)
        done.append(dst)
        eta = (len(scenes) - i) * (time.perf_counter() - t0) / i
        print(f"rendered {i}/{len(scenes)} scenes, ETA {eta:.0f} s", file=sys.stderr, flush=True)
    return done


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=Path, required=True, help="a folder of scene folders")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--config", type=Path, required=True, help="the config whose render block to start from")
    ap.add_argument("--set", dest="settings", action="append", default=[], metavar="render.KEY=VALUE",
                    help="a render setting (VALUE as YAML); repeatable")
    args = ap.parse_args(argv)
    from psdfactory import PsdError
    from psdfactory.io import is_within

    scenes = sorted(p.parent for p in args.scenes.glob("*/poses.parquet") if (p.parent / "spec.json").exists())
    if not scenes:
        ap.error(f"no scene folders (spec.json, poses.parquet) under {args.scenes}")
    out = args.out.resolve()
    if out == args.scenes.resolve() or any(is_within(out, s) for s in scenes):
        ap.error(f"--out {args.out} is --scenes or inside one of its scenes: the sources would be written into")
    if out.exists() and not out.is_dir():
        ap.error(f"--out {args.out} is a file: give a folder")
    try:
        params = render_settings(args.config, args.settings)
        relook(scenes, args.out, params)
    except PsdError as e:
        ap.exit(1, f"relook.py: {e}\n")
    print(f"{len(scenes)} scenes in {args.out}: backend {params['backend']}, {params['resolution']} px")
    return 0


if __name__ == "__main__":
    sys.exit(main())
