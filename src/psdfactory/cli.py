"""The one command-line entry point: ``psdfactory <command> ...``. The Snakemake rules call it."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from . import PsdError, __version__


def _params(text: str) -> dict:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        raise PsdError(f"--params is not valid JSON: {e}") from None
    if not isinstance(value, dict):
        raise PsdError("--params must be a JSON object")
    return value


def cmd_sample(a: argparse.Namespace) -> None:
    from .scene import run_sample

    run_sample(_params(a.params), Path(a.scene_dir))


def cmd_simulate(a: argparse.Namespace) -> None:
    from .scene import run_simulate

    run_simulate(_params(a.params), Path(a.scene_dir))


def cmd_render(a: argparse.Namespace) -> None:
    from .scene import run_render

    run_render(_params(a.params), Path(a.scene_dir))


def cmd_label(a: argparse.Namespace) -> None:
    from .scene import run_label

    run_label(_params(a.params), Path(a.scene_dir))


def cmd_manifest(a: argparse.Namespace) -> None:
    from .manifest import write_shard

    fractions = _params(a.params)["split"]
    scenes = write_shard([Path(d) for d in a.scene_dirs], Path(a.results), fractions, Path(a.scenes_out), Path(a.particles_out))
    print(f"wrote {a.scenes_out}: {scenes.num_rows} scenes")


def cmd_show(a: argparse.Namespace) -> None:
    from .show import contact_sheet

    out = contact_sheet(Path(a.results), a.dataset, Path(a.out), a.n)
    print(f"wrote {out}")


def cmd_check_config(a: argparse.Namespace) -> None:
    from .config import load_config

    cfg = load_config(Path(a.configfile))
    n = sum(d["n_scenes"] for d in cfg["datasets"].values())
    print(f"{a.configfile}: OK ({len(cfg['datasets'])} datasets, {n} scenes)")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="psdfactory", description=__doc__)
    ap.add_argument("--version", action="version", version=f"psdfactory {__version__}")
    sub = ap.add_subparsers(dest="command", required=True)

    for name, fn, helptext in [
        ("sample", cmd_sample, "draw a scene's particles → spec.json, geometry.npz"),
        ("simulate", cmd_simulate, "settle the particles with pybullet → poses.parquet, simulate.json"),
        ("render", cmd_render, "render the bed → image.png, mask.png, render.json"),
        ("label", cmd_label, "PSD labels → labels.json, particles.parquet"),
    ]:
        p = sub.add_parser(name, help=helptext)
        p.add_argument("--params", required=True, help="the stage's config slice as JSON")
        p.add_argument("scene_dir")
        p.set_defaults(func=fn)

    p = sub.add_parser("manifest", help="gather scenes into one Parquet shard")
    p.add_argument("--params", required=True, help='JSON with "split" fractions')
    p.add_argument("--results", required=True, help="results root (image paths are relative to it)")
    p.add_argument("--scenes-out", required=True)
    p.add_argument("--particles-out", required=True)
    p.add_argument("scene_dirs", nargs="*")
    p.set_defaults(func=cmd_manifest)

    p = sub.add_parser("show", help="contact sheet of a few scenes with masks and labels")
    p.add_argument("--results", default="results")
    p.add_argument("--dataset", default="train")
    p.add_argument("-n", type=int, default=6, help="number of scenes")
    p.add_argument("--out", default="contact_sheet.png")
    p.set_defaults(func=cmd_show)

    p = sub.add_parser("check-config", help="validate a config file against the schema")
    p.add_argument("configfile")
    p.set_defaults(func=cmd_check_config)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except PsdError as e:
        print(f"psdfactory {args.command}: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
