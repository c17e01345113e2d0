"""The one command-line entry point: ``psdfactory <command> ...``. The Snakemake rules call it."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import traceback
from pathlib import Path

from . import PsdError, __version__
from .config import PREDICT_RUNTIMES, PREDICT_TILE_PX
from .packs import IMAGE_FORMATS, PackSpec
from .psd import GRAIN_WEIGHTINGS, SIZE_DEFINITIONS

logger = logging.getLogger(__name__)
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def _params(text: str) -> dict:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        raise PsdError(f"--params is not valid JSON: {e}") from None
    if not isinstance(value, dict):
        raise PsdError("--params must be a JSON object")
    return value


def cmd_stage(a: argparse.Namespace) -> None:
    from .scene.stages import run_scenes

    run_scenes(a.command, _params(a.params), [Path(d) for d in a.scene_dirs], skip_up_to_date=a.skip_up_to_date,
               jobs=a.jobs, stamp=Path(a.stamp) if a.stamp else None)


def cmd_manifest(a: argparse.Namespace) -> None:
    from .manifest import write_shard

    fractions = _params(a.params)["split"]
    scenes = write_shard([Path(d) for d in a.scene_dirs], Path(a.results), fractions, Path(a.scenes_out),
                         Path(a.particles_out))
    logger.info(f"wrote {a.scenes_out}: {scenes.num_rows} scenes")


def cmd_show(a: argparse.Namespace) -> None:
    from .io import is_within
    from .scene.show import contact_sheet

    if Path(a.out).is_dir():
        raise PsdError(f"--out {a.out} is a folder; give a .png file name")
    scenes = Path(a.results) / a.dataset / "scenes"
    if is_within(a.out, scenes):
        raise PsdError(f"--out {a.out} is inside the scenes it shows ({scenes}); write the sheet elsewhere")
    if Path(a.out).suffix.lower() != ".png":
        raise PsdError(f"--out {a.out}: must end in .png")
    out = contact_sheet(Path(a.results), a.dataset, Path(a.out), a.n)
    logger.info(f"wrote {out}")


def cmd_pack(a: argparse.Namespace) -> int | None:
    if a.verify:
        from .packs import verify

        n, problems = verify(Path(a.verify))
        for line in problems:
            print(line)
        print(f"{a.verify}: {n - len(problems)} of {n} shards as the index says"
              + ("" if not problems else "; copy the others again, or pack again"))
        return 1 if problems else 0
    from .learn.shards import pack

    spec = PackSpec(size=a.size, image_format=a.format, quality=a.quality, masks=not a.no_masks,
                    shard_scenes=a.shard_scenes, seed=a.seed)
    pack(Path(a.results), a.datasets, Path(a.out), spec, tuple(a.splits) if a.splits else None, jobs=a.jobs)


def cmd_compare_backends(a: argparse.Namespace) -> None:
    from .scene.show import compare_backends

    summary = compare_backends(Path(a.results), a.dataset, a.n, _params(a.params), Path(a.out_dir))
    for r in summary["scenes"]:
        logger.info(f"{r['scene_id']}: tiny {r['seconds_tiny']:.1f} s, cycles {r['seconds_cycles']:.1f} s, "
                    f"masks agree on {100 * r['mask_agreement']:.1f} % of pixels "
                    f"({100 * r['mask_agreement_off_edges']:.2f} % off edges)")


def cmd_check_config(a: argparse.Namespace) -> None:
    from .config import load_config
    from .learn.registry import check_architectures
    from .photoset import check

    cfg = load_config(Path(a.configfile))
    try:
        check_architectures(cfg["train"]["architectures"])
        photo_sets = check(cfg)  # their files, relative to the working directory as in a run
    except PsdError as e:
        raise PsdError(f"{a.configfile}: invalid config: {e}") from None
    n = sum(d["n_scenes"] for d in cfg["datasets"].values())
    photos = sum(len(s.photos) for s in photo_sets.values())
    also = f", {len(photo_sets)} photo set{'s' * (len(photo_sets) != 1)} of {photos} photos" if photo_sets else ""
    print(f"{a.configfile}: OK ({len(cfg['datasets'])} datasets, {n} scenes{also})")


def cmd_train(a: argparse.Namespace) -> None:
    from .learn.distributed import ranks_from_env
    from .learn.train import train_from_params

    if not ranks_from_env().main:  # one of several torchrun processes: rank 0 logs the progress
        logging.getLogger("psdfactory").setLevel(logging.WARNING)
    _threads(a.threads)
    train_from_params(_params(a.params), Path(a.results), Path(a.out_dir),
                      Path(a.pack) if a.pack else None, a.loader_workers)


def cmd_evaluate(a: argparse.Namespace) -> None:
    from .learn.evaluate import evaluate, plot_history

    p = _params(a.params)
    _threads(a.threads)
    out = Path(a.out_dir)
    evaluate(Path(a.model), Path(a.results), p["datasets"], out, precision=p.get("precision", "fp32"))
    if a.history:
        plot_history(Path(a.history), p.get("arch", Path(a.model).parent.name), out / "loss_curve.png")


def cmd_evaluate_photos(a: argparse.Namespace) -> None:
    from .deploy.photos import evaluate_photos
    from .photoset import resolve

    p = _params(a.params)
    spec = p.get("photoset")
    if not isinstance(spec, dict) or not isinstance(spec.get("name"), str):
        raise PsdError('--params must hold "photoset": a photo set\'s config slice with its name '
                       "(config.photo_params)")
    _threads(a.threads)
    evaluate_photos(Path(a.model), resolve(spec["name"], spec), Path(a.out_dir),
                    precision=p.get("precision", "fp32"))


def cmd_benchmark(a: argparse.Namespace) -> None:
    from .deploy.benchmark import benchmark
    from .io import write_json

    p = _params(a.params)
    _threads(a.threads)
    res = benchmark(Path(a.model), Path(a.results), p["dataset"], p["batch_size"], p["seconds"], p["repeats"])
    write_json(Path(a.out), res)


def cmd_report(a: argparse.Namespace) -> None:
    from .io import same_file
    from .report import ReportInputs, build_report

    outputs = {"--html": Path(a.html), "--md": Path(a.md)}
    reads = [a.config_json, *a.metrics, *a.scatters, *a.histories, *a.bench, *a.manifests, *a.contact_sheets,
             *(a.compare or []), *a.ceilings, *a.photos, a.spread]
    if outputs["--html"].suffix.lower() != ".html" or outputs["--md"].suffix.lower() != ".md":
        raise PsdError(f"--html {a.html} must end in .html and --md {a.md} in .md")
    if same_file(outputs["--html"], outputs["--md"]):
        raise PsdError("--html and --md are the same file; give each its own")
    for flag, out in outputs.items():
        hit = next((r for r in reads if r and same_file(out, Path(r))), None)
        if hit:
            raise PsdError(f"{flag} {out} is also an input of the report ({hit}); give the report its own file")
    if a.config_json:
        from .io import read_json

        cfg = read_json(a.config_json)
        if not isinstance(cfg, dict):
            raise PsdError(f"--config-json {a.config_json} must hold a JSON object (the validated config)")
    else:
        cfg = _params(a.params)
    inputs = ReportInputs.from_lists(cfg, a.metrics, a.scatters, a.histories, a.bench, a.manifests,
                                     a.contact_sheets, a.compare, a.ceilings, a.photos, a.spread)
    build_report(cfg, inputs, Path(a.html), Path(a.md))
    logger.info(f"wrote {a.html} and {a.md}")


def cmd_ceiling(a: argparse.Namespace) -> None:
    from .io import write_json
    from .learn.ceiling import ceilings_from_manifests

    p = _params(a.params)
    reference = None
    if p.get("reference"):
        if not a.reference_scenes or not a.reference_particles:
            raise PsdError(f"{a.dataset}: its ceilings are fitted on {p['reference']['dataset']}'s scenes: "
                           "give that dataset's manifest shards with --reference-scenes and --reference-particles")
        reference = {**p["reference"], "scenes": a.reference_scenes, "particles": a.reference_particles}
    c = ceilings_from_manifests(a.scenes, a.particles, tuple(p["bounds"]), p["visible_min_px"], p.get("folds", 5),
                                results_root=Path(a.results) if a.results else None, reference=reference)
    c["dataset"] = a.dataset
    write_json(Path(a.out), c)
    for kind in ("visible", "footprints", "sampling"):
        if c.get(kind):
            r2 = " / ".join(f"{v:.3f}" for v in c[kind].values())
            logger.info(f"{a.dataset}: {kind.removesuffix('s')} ceiling R² {r2}")
    if c.get("note"):
        logger.info(f"{a.dataset}: {c['note']}")


def positive_int(text: str) -> int:
    """argparse type: a whole number of at least 1."""
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: give a whole number of at least 1")
    return v


MM_PER_PX_RANGE = (1e-4, 1e3)  # what --mm-per-px may be: from a microscope to a drone


def mm_per_px_arg(text: str) -> float:
    """argparse type of --mm-per-px: a finite number within MM_PER_PX_RANGE."""
    import math

    try:
        v = float(text)
    except ValueError:
        v = math.nan
    lo, hi = MM_PER_PX_RANGE
    if not (math.isfinite(v) and lo <= v <= hi):
        raise argparse.ArgumentTypeError(f"{text!r}: give the images' scale as a number of mm per pixel from {lo:g} "
                                         f"to {hi:g} (measure it on a ruler or scale card in the photo)")
    return v


def log_problem(a: argparse.Namespace) -> str | None:
    """Why --log may not be written: it is one of the command's input or output files."""
    from .io import same_file

    log = Path(a.log)
    if log.is_dir():
        return f"--log {log} is a folder; give a file name"
    named = []
    for k, v in vars(a).items():  # every argument that may name a file: a path, or a list of them
        if k not in ("log", "params", "command") and isinstance(v, str | list):
            named += [x for x in (v if isinstance(v, list) else [v]) if isinstance(x, str) and x]
    for p in named:
        if same_file(log, Path(p)):
            return f"--log {log} is also {p}, which the command reads or writes: give the log its own file"
    return None


def cmd_predict(a: argparse.Namespace) -> int:
    from .deploy.predict import check_outputs, partial_path, stream_predictions
    from .learn.runtime import pick_device
    from .psd import TARGETS

    paths = {k: Path(v) if v else None for k, v in (("out", a.out), ("masks_dir", a.masks),
                                                   ("overlay_dir", a.overlay), ("particles_out", a.particles),
                                                   ("log", a.log))}
    check_outputs(Path(a.model), a.images, **paths)  # before any work, and before the table's header
    pick_device(a.device)

    header = []

    def emit(r: dict) -> None:  # the table is the command's output (stdout), a row as soon as it is made
        if not header:  # printed with the first row: nothing is printed before an error
            header.append(True)
            print(f"{'image':<50} " + " ".join(f"{t:>8}" for t in TARGETS) + f"  ({r['size_definition']}, "
                  f"{r['weighting']}-weighted)", flush=True)
        if r["error"]:
            print(f"{r['image']:<50} error: {r['error']}", flush=True)
        else:
            doubt = "  ⚠ " + r["warning"] if r.get("warning") else ""  # as the log says it, and the file
            print(f"{r['image']:<50} " + " ".join(f"{r[t]:>8.3f}" for t in TARGETS) + doubt, flush=True)

    out = Path(a.out) if a.out else None
    try:
        n, failed = stream_predictions(Path(a.model), a.images, out, a.mm_per_px, device=a.device, resume=a.resume,
                                       emit=emit, overlay_dir=Path(a.overlay) if a.overlay else None,
                                       masks_dir=Path(a.masks) if a.masks else None,
                                       particles_out=Path(a.particles) if a.particles else None,
                                       size_definition=a.size_definition, weighting=a.weighting, tile=a.tile,
                                       runtime=a.runtime, auto_scale=a.auto_scale, roi=a.roi)
    except KeyboardInterrupt:
        if out is not None:
            logger.error(f"psdfactory predict: interrupted; the rows done so far are in {partial_path(out)} "
                         "(rerun with --resume to go on)")
        return 130
    if out is not None:
        logger.info(f"wrote {out}")
    if failed:
        logger.error(f"psdfactory predict: {failed} of {n} images failed (each one's row says why)")
    return 1 if failed else 0


def cmd_calibrate(a: argparse.Namespace) -> None:
    from .deploy.calibrate import calibrate, table_lines
    from .learn.runtime import pick_device

    pick_device(a.device)
    block = calibrate(Path(a.model), Path(a.reference), a.images, Path(a.out), a.mm_per_px,
                      size_definition=a.size_definition, device=a.device, auto_scale=a.auto_scale,
                      weighting=a.weighting, roi=a.roi)
    print("\n".join(table_lines(block)), flush=True)


def cmd_export(a: argparse.Namespace) -> None:
    from .deploy.export import export

    export(Path(a.model), Path(a.out_dir), int8_results=Path(a.int8) if a.int8 else None, dataset=a.dataset,
           max_r2_change=a.int8_max_r2_change)


def _threads(n: int) -> None:
    if n:
        import torch

        torch.set_num_threads(n)


# --- the command line: two groups of commands, help on every flag, examples -------------------------------------

HELP_COLUMNS = 100  # the help is wrapped to the terminal, and never wider than this

# What a person runs, in the order `psdfactory --help` lists them, with the one line it shows.
USER_COMMANDS = {
    "predict": "read d10/d50/d90 (mm) off photos with a trained model → table, CSV or JSON",
    "export": "ONNX and TorchScript copies of a model (int8 too), checked against PyTorch",
    "calibrate": "correct a model against reference samples (sieved or lab-measured d10/d50/d90) → a calibrated model",
    "show": "contact sheet of a dataset's scenes: images, masks and labels side by side",
    "pack": "a dataset's scenes as WebDataset tar shards, for training on many GPUs or from object storage",
    "check-config": "validate a config file against the schema, without running anything",
}
# The steps of the workflow (rules/*.smk call them, most with --params), in the pipeline's order,
# with the rule file that calls each.
WORKFLOW_COMMANDS = {
    "sample": ("draw each scene's particles → spec.json, geometry.npz", "rules/sample.smk"),
    "simulate": ("settle the particles with pybullet → poses.parquet, simulate.json", "rules/simulate.smk"),
    "render": ("render the bed → image.png, mask.png, render.json", "rules/render.smk"),
    "label": ("PSD labels of each scene → labels.json, particles.parquet", "rules/label.smk"),
    "manifest": ("gather scenes into one Parquet manifest shard", "rules/manifest.smk"),
    "ceiling": ("what a dataset's images allow: cross-validated R² ceilings per target", "rules/evaluate.smk"),
    "train": ("train one architecture → model.pt, history.csv, TensorBoard logs", "rules/train.smk"),
    "evaluate": ("metrics, predictions and plots of a trained model", "rules/evaluate.smk"),
    "evaluate-photos": ("a trained model on a photo set: grains and PSD vs the reference, overlays",
                        "rules/photos.smk"),
    "benchmark": ("inference speed (fp32 eager vs the fast path) and accuracy change", "rules/benchmark.smk"),
    "compare-backends": ("render a few scenes with both render backends, side by side", "rules/report.smk"),
    "report": ("the final HTML report and its Markdown twin", "rules/report.smk"),
}
WORKFLOW_HEADING = "workflow commands (called by the Snakemake rules; you rarely run these)"
COMMANDS = (*USER_COMMANDS, *WORKFLOW_COMMANDS)

DESCRIPTION = ("Synthetic particle-bed images, and models trained on them that read a particle size distribution "
               "(d10/d50/d90 in mm) off a photo. `snakemake -j2` runs the whole factory (scenes, models, report); "
               "the commands use what it made, and the workflow commands are its steps.")

EXAMPLES = {
    None: [
        "snakemake -j2 --configfile config/config.yaml      # the whole factory: scenes → models → report",
        "psdfactory check-config my.yaml                    # validate a config before a run",
        "psdfactory show --results results --dataset train -n 8 --out sheet.png",
        "psdfactory predict --model results/models/instances/model.pt --mm-per-px 0.288 photos/",
        "psdfactory export --model results/models/efficientnet_b0/model.pt --out-dir deploy/",
        "psdfactory predict --help                          # a command's options and examples",
    ],
    "predict": [
        "psdfactory predict --model results/models/efficientnet_b0/model.pt photos/ one.jpg",
        "psdfactory predict --model results/models/instances/model.pt --mm-per-px 0.288 \\",
        "    --overlay overlays/ --particles grains.csv --out psd.csv photos/",
        "psdfactory predict --model results/models/instances/model.pt --resume --out psd.csv photos/",
        "psdfactory predict --model deploy/model.int8.onnx --size-definition sieve photos/",
        "psdfactory predict --model results/models/resnet50/model.pt --device auto --out psd.json photos/",
    ],
    "export": [
        "psdfactory export --model results/models/efficientnet_b0/model.pt --out-dir deploy/",
        "psdfactory export --model results/models/efficientnet_b0/model.pt --out-dir deploy/ \\",
        "    --int8 results                                 # + model.int8.onnx",
        "psdfactory predict --model deploy/model.int8.onnx photos/      # then: predict with the export",
    ],
    "calibrate": [
        "psdfactory calibrate --model results/models/instances/model.pt --reference sieved.csv \\",
        "    --mm-per-px 0.288 --out calibrated.pt photos/   # sieved.csv: image,d10_mm,d50_mm,d90_mm",
        "psdfactory predict --model calibrated.pt --mm-per-px 0.288 new/   # then: corrected readings",
        "psdfactory export --model calibrated.pt --out-dir deploy/      # the ONNX export applies it too",
    ],
    "pack": [
        "psdfactory pack --results results --datasets train --out packs/train224/   # 224 px JPEG, masks",
        "psdfactory pack --datasets train train_cycles --size 299 --shard-scenes 5000 --jobs 8 \\",
        "    --out packs/incv3/                            # both renderers mixed, for InceptionV3",
        "psdfactory pack --verify /scratch/packs/train224/   # a copy checked against its index",
    ],
    "show": [
        "psdfactory show                                    # results/train → contact_sheet.png",
        "psdfactory show --results results --dataset ood_test -n 8 --out ood_sheet.png",
    ],
    "check-config": [
        "psdfactory check-config config/config.yaml",
        "psdfactory check-config my.yaml && snakemake -j2 --configfile my.yaml",
    ],
}


def _width() -> int:
    """The help's width: argparse's (the terminal's, less 2), at most HELP_COLUMNS - 2."""
    import shutil

    return max(40, min(shutil.get_terminal_size().columns, HELP_COLUMNS) - 2)


def _text(*paragraphs: str) -> str:
    """Paragraphs wrapped to the help's width (the help formatter leaves descriptions as they are,
    so that the examples keep their lines)."""
    import textwrap

    return "\n\n".join(textwrap.fill(p, _width(), break_on_hyphens=False) for p in paragraphs)


def _examples(command: str | None) -> str:
    return "examples:\n" + "\n".join(f"  {line}" for line in EXAMPLES[command])


def _command_list() -> str:
    """The two groups of commands of ``psdfactory --help``, each name with its one line."""
    import textwrap

    name_width = max(map(len, COMMANDS)) + 4
    blocks = []
    for heading, summaries in (("commands", USER_COMMANDS),
                               (WORKFLOW_HEADING, {k: v[0] for k, v in WORKFLOW_COMMANDS.items()})):
        lines = [f"{heading}:"]
        for name, summary in summaries.items():
            lines += textwrap.wrap(summary, _width(), initial_indent=f"  {name:<{name_width - 2}}",
                                   subsequent_indent=" " * name_width, break_on_hyphens=False)
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


class _Help(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Descriptions and epilogs as written (pre-wrapped text, examples line by line), each option's
    default after its help where it has one worth saying, at most HELP_COLUMNS wide."""

    def __init__(self, prog: str) -> None:
        super().__init__(prog, max_help_position=30, width=_width())

    def _split_lines(self, text: str, width: int) -> list[str]:
        import textwrap

        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)  # not "feret-" / "max"

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False or action.default == []:
            return action.help  # no default to state: "(default: None)" says nothing
        return super()._get_help_string(action)


class _Parser(argparse.ArgumentParser):
    """An argparse parser whose usage errors are one line: what is wrong, and where the help is."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", _Help)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> None:
        import re

        if message == "the following arguments are required: <command>":
            message = "no command given"
        elif (m := re.match(r"argument <command>: invalid choice: '([^']*)'", message)) is not None:
            import difflib

            close = difflib.get_close_matches(m[1], COMMANDS, n=1)
            message = f"unknown command {m[1]!r}" + (f": did you mean {close[0]}?" if close else "")
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def parse_args(self, args=None, namespace=None) -> argparse.Namespace:
        """argparse's, with arguments it does not know refused by the command's parser (whose help
        has the command's options), not the main one."""
        ns, extras = self.parse_known_args(args, namespace)
        if extras:
            parser = getattr(self, "commands", {}).get(getattr(ns, "command", None), self)
            parser.error(f"unrecognized arguments: {' '.join(extras)}")
        return ns


def _scale_arg(p: argparse.ArgumentParser, then: str) -> None:
    p.add_argument("--mm-per-px", type=mm_per_px_arg, metavar="MM",
                   help="scale of the images in mm per pixel (1e-4 to 1e3)" + then)


def roi_arg(text: str):
    """argparse type of --roi: a `photoset.Region`."""
    from .photoset import Region

    try:
        return Region.parse(text)
    except PsdError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix(f"--roi {text!r}: ")) from None


def _roi_arg(p: argparse.ArgumentParser, then: str) -> None:
    p.add_argument("--roi", type=roi_arg, metavar="L,T,R,B",
                   help="read only this box of every photo: LEFT,TOP,RIGHT,BOTTOM in px of the photo as taken "
                   "(upright, full size, as an image viewer shows it; right and bottom one past the box), as if the "
                   "photo were cropped to it. Leave out a scale card, a ruler or a belt's edge: they are not grains, "
                   "and a model may take them for some. Grains cut by the box's sides count as cut by a border" + then)


def _auto_scale_arg(p: argparse.ArgumentParser, then: str) -> None:
    p.add_argument("--auto-scale", action=argparse.BooleanOptionalAction, default=None,
                   help="instance models, with --mm-per-px: where a photo's grains look larger than the grains the "
                   "model trained on (cobbles under a model of finer rock), read it at the coarser scale that shows "
                   "them at that size, as a first look at half the model's scale finds; the log says when. "
                   "Grains larger than the network sees at once are otherwise cut along their texture. Default: "
                   "the model's recipe (train.instances.auto_scale; on for config/gravel.yaml, off for the table "
                   "scenes of the default config, whose looks can make grains look larger than they are: "
                   "docs/photos.md)." + then)


def _threads_arg(p: argparse.ArgumentParser, out_dir: str | None = None) -> None:
    """--threads, and with `out_dir` (its help) --out-dir: what a PyTorch job takes."""
    if out_dir:
        p.add_argument("--out-dir", required=True, metavar="DIR", help=out_dir)
    p.add_argument("--threads", type=int, default=0, metavar="N",
                   help="PyTorch's CPU threads, 0 for PyTorch's own choice")


def _job_args(p: argparse.ArgumentParser, params_help: str, model_help: str | None = None) -> None:
    """--params, --model (with `model_help`) and --results: what a training-side job takes."""
    p.add_argument("--params", required=True, metavar="JSON", help=params_help)
    if model_help:
        p.add_argument("--model", required=True, metavar="FILE", help=model_help)
    p.add_argument("--results", required=True, metavar="DIR", help="the results root holding the datasets")


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="psdfactory", usage="psdfactory [-h] [--version] [-q | -v] [--log FILE] <command> ...",
                 description=_text(DESCRIPTION) + "\n\n" + _command_list(), epilog=_examples(None))
    ap.add_argument("--version", action="version", version=f"psdfactory {__version__}",
                    help="print the version and exit")
    loud = ap.add_mutually_exclusive_group()
    loud.add_argument("-q", "--quiet", action="store_true", help="log warnings and errors only (no progress bars)")
    loud.add_argument("-v", "--verbose", action="store_true", help="log debugging detail too")
    ap.add_argument("--log", metavar="FILE",
                    help="write everything the command prints (libraries' output too) to FILE, and its verdict "
                         "line on failure to stderr as well: the rules' job logs, which a full disk can swallow")
    # listed by the description, in two groups; `prog` given, or the usage above would become its prefix
    sub = ap.add_subparsers(dest="command", required=True, metavar="<command>", help=argparse.SUPPRESS,
                            prog="psdfactory")

    def user(name: str, *about: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, description=_text(USER_COMMANDS[name][0].upper() + USER_COMMANDS[name][1:] + ".",
                                                      *about), epilog=_examples(name))

    def workflow(name: str, *about: str) -> argparse.ArgumentParser:
        summary, rules = WORKFLOW_COMMANDS[name]
        return sub.add_parser(name, description=_text(summary[0].upper() + summary[1:] + ".", *about,
                                                      f"A workflow step: {rules} calls it; you rarely run it."))

    # --- what a person runs ---
    p = user("predict",
             "The table goes to stdout, a row per image as soon as it is done; progress and errors go to stderr. "
             "Exit status: 0, 1 when some images failed (each one's row says why), 2 when nothing could start "
             "(the one line says why), 130 when interrupted.")
    p.add_argument("--model", required=True, metavar="FILE",
                   help="a model.pt written by training (results/models/<arch>/model.pt), or an .onnx written by "
                        "export (fp32 or int8, with its meta.json beside it)")
    _scale_arg(p, "; they are rescaled to the model's scale (default: the images are at the model's scale, that "
                  "of its training images)")
    p.add_argument("--out", metavar="FILE",
                   help="write the predictions to this .csv or .json file (rows go to <out>.partial.csv as they "
                        "come; it becomes <out> when every image is done)")
    p.add_argument("--resume", action="store_true",
                   help="skip the images that already have a prediction in --out or its .partial.csv "
                        "(failed ones are retried)")
    p.add_argument("--device", default="cpu", metavar="DEVICE",
                   help="where the model runs: cpu, auto (cuda when there is one), cuda, cuda:N (e.g. cuda:1) or mps")
    p.add_argument("--runtime", choices=PREDICT_RUNTIMES, default="auto",
                   help="what runs a model.pt's network on the CPU: torch (PyTorch), onnx (an ONNX Runtime copy, "
                   "made once and kept in ~/.cache/psdfactory or $PSDFACTORY_CACHE), or auto: the faster of the two "
                   "as timed once on this machine (default: auto; on a GPU PyTorch runs it; an .onnx model always "
                   "runs in ONNX Runtime)")
    p.add_argument("--overlay", metavar="DIR", help="instance models: write each image with its particles' outlines "
                   "and sizes (mm) drawn on as DIR/<image stem>.png")
    p.add_argument("--masks", metavar="DIR", help="instance models: write each image's instance mask as "
                   "DIR/<image stem>.png (16-bit, 0 = background, k = one particle)")
    p.add_argument("--particles", metavar="FILE", help="instance models: write every grain found to this CSV, "
                   "measured in mm at the photo's scale (image, id, centroid_row_px, centroid_col_px, area_mm2, "
                   "ecd_mm, ellipse_major_mm, ellipse_minor_mm, feret_min_mm, feret_max_mm, sieve_size_mm, "
                   "volume_mm3, touches_edge, mask_mm_per_px; docs/photos.md)")
    p.add_argument("--size-definition", choices=SIZE_DEFINITIONS, metavar="NAME",
                   help="what d10/d50/d90 are of: " + ", ".join(SIZE_DEFINITIONS) + " (default: the definition "
                   "the model was trained on, or a calibrated model's, in the CSV's size_definition column). An "
                   "instance model also estimates the other solid definitions (sieve, b-axis, c-axis, esd) and "
                   "measures feret-min, feret-max and ecd on the whole grains it finds; a CNN reads only its own; a "
                   "calibrated model only its calibration's")
    p.add_argument("--weighting", choices=GRAIN_WEIGHTINGS, metavar="NAME",
                   help="what the percentiles count: " + ", ".join(GRAIN_WEIGHTINGS) + " (grains, their footprint "
                   "area, their volume; default: the model's training weighting, or a calibrated model's, in the "
                   "CSV's weighting column). An instance model weights feret-min, feret-max and ecd any way "
                   "(area-weighted grains of a photo compare with a Wolman grid count, volume-weighted with a sieve "
                   "analysis); its other definitions and a CNN give only the weighting they were trained on, a "
                   "calibrated model only its calibration's (calibrate --weighting)")
    p.add_argument("--tile", type=positive_int, default=PREDICT_TILE_PX, metavar="PX",
                   help="instance models: run an image larger than this at the network's scale in overlapping "
                   "tiles of this side (px, a multiple of 32), stitched into one result: memory for the network "
                   f"stays that of one tile (default: {PREDICT_TILE_PX})")
    _auto_scale_arg(p, "")
    _roi_arg(p, "; --overlay and --masks show the box, --particles gives positions in the photo's pixels")
    p.add_argument("images", nargs="+", metavar="IMAGE",
                   help="image files (.png, .jpg, .tif, .bmp, .webp) and/or folders of them, subfolders included")
    p.set_defaults(func=cmd_predict)

    p = user("export", "The files are written into a new folder that replaces --out-dir only when every one is "
             "made and checked: a failed export leaves --out-dir as it was.")
    p.add_argument("--model", required=True, metavar="FILE",
                   help="the model.pt to export (results/models/<arch>/model.pt)")
    p.add_argument("--out-dir", required=True, metavar="DIR",
                   help="the folder to write model.onnx, model.torchscript.pt, meta.json and export.json to "
                        "(the instance model: model.onnx, meta.json, export.json)")
    p.add_argument("--int8", metavar="RESULTS",
                   help="also model.int8.onnx, calibrated on this results root's training images")
    p.add_argument("--dataset", default="train", metavar="NAME",
                   help="with --int8: the dataset (of the config's datasets) to calibrate and check int8 on")
    p.add_argument("--int8-max-r2-change", type=float, default=None, metavar="R2",
                   help="refuse the int8 model if the R² of any target on the test split moves more than this "
                        "(default: the benchmark's accuracy budget, 0.005)")
    p.set_defaults(func=cmd_export)

    p = user("calibrate",
             "Each reference image is predicted with the model (as predict does), and a correction from the "
             "model's reading to the reference is fitted per target (d10, d50, d90): affine (least squares) below "
             "10 references, isotonic (monotone, extrapolated linearly) from 10 on; the corrected d-values are "
             "sorted (d10 <= d50 <= d90). The table on stdout gives its leave-one-out error (each reference "
             "corrected by the fit on the others) beside the uncalibrated error. --out gets the same model with "
             "the calibration in its meta: predict and an export of it apply the correction, in the size "
             "definition and weighting it was fitted in (docs/calibration.md).")
    p.add_argument("--model", required=True, metavar="FILE",
                   help="the model.pt to calibrate (results/models/<arch>/model.pt); a calibrated one is "
                        "calibrated afresh on its uncalibrated readings")
    p.add_argument("--reference", required=True, metavar="CSV",
                   help="the reference samples: a CSV with columns image,d10_mm,d50_mm,d90_mm (at least 3 rows); "
                        "image is matched to the IMAGEs by path, else by file name, else by file name without "
                        "suffix, one-to-one")
    _scale_arg(p, ", as for predict; use the same scale when predicting with the calibrated model (default: the "
                  "model's scale)")
    p.add_argument("--size-definition", choices=SIZE_DEFINITIONS, metavar="NAME",
                   help="what the references' d10/d50/d90 are of: " + ", ".join(SIZE_DEFINITIONS) + " (default: "
                   "the definition the model was trained on); the calibrated model is corrected in it only")
    p.add_argument("--weighting", choices=GRAIN_WEIGHTINGS, metavar="NAME",
                   help="what the references' percentiles count: " + ", ".join(GRAIN_WEIGHTINGS) + " (a sieve "
                   "analysis counts mass: volume; a Wolman grid count: area; default: the model's weighting of "
                   "that definition). Where the model does not read it, an instance model's correction takes its "
                   "grains measured in that weighting (min Feret width; ecd for esd), a CNN's its own reading")
    p.add_argument("--device", default="cpu", metavar="DEVICE",
                   help="where the model runs: cpu, auto (cuda when there is one), cuda, cuda:N or mps")
    _auto_scale_arg(p, " Calibrate as you will predict: the calibration records which")
    _roi_arg(p, "; predict with the calibrated model on the same box")
    p.add_argument("--out", required=True, metavar="FILE",
                   help="the calibrated model to write (.pt; not the model itself, the reference table or an image)")
    p.add_argument("images", nargs="+", metavar="IMAGE",
                   help="the reference samples' images: files and/or folders of them, subfolders included")
    p.set_defaults(func=cmd_calibrate)

    p = user("show", "It reads the dataset's manifest (results/<dataset>/manifest): run the workflow first. "
             "The workflow makes one per dataset too (results/<dataset>/contact_sheet.png, rules/manifest.smk).")
    p.add_argument("--results", default="results", metavar="DIR", help="the results root of a run: the config's "
                   "`results` folder")
    p.add_argument("--dataset", default="train", metavar="NAME", help="the dataset to show (one of the config's "
                   "datasets)")
    p.add_argument("-n", type=positive_int, default=6, metavar="N", help="number of scenes (at least 1)")
    p.add_argument("--out", default="contact_sheet.png", metavar="FILE",
                   help="the contact sheet, a .png file outside the scenes it shows")
    p.set_defaults(func=cmd_show)

    p = user("pack", "Every scene of the chosen splits becomes one sample of a tar shard: its image resized to the "
             "networks' input size (--size), its manifest row as JSON (targets, size definition, the scale at the "
             "packed size) and, unless --no-masks, its instance mask at that size and its particles' sizes. The "
             "scenes of all the datasets are mixed in a seeded order. The pack is written beside --out and "
             "replaces it when every shard is done, index.json last (shards, scene counts, bytes, SHA-256). Read "
             "it with psdfactory.learn.shards.ShardScenes (each DDP rank and loader worker its own shards, the "
             "same number of samples on every rank) or any WebDataset reader (docs/scale.md).")
    p.add_argument("--results", default="results", metavar="DIR", help="the results root of a run (its manifests)")
    p.add_argument("--datasets", nargs="+", default=["train"], metavar="NAME",
                   help="the datasets to pack together (of the config's datasets; the labels must be of one size "
                        "definition)")
    p.add_argument("--splits", nargs="+", metavar="SPLIT",
                   help="the splits to pack, each into shards of its own (default: every split of the manifests)")
    p.add_argument("--size", type=positive_int, default=PackSpec.size, metavar="PX",
                   help="images and masks resized to PX x PX (the networks' input size: 224, 299 for InceptionV3)")
    p.add_argument("--format", choices=IMAGE_FORMATS, default=PackSpec.image_format,
                   help="the images' format: jpg (small, lossy) or png (lossless)")
    p.add_argument("--quality", type=positive_int, default=PackSpec.quality, metavar="Q", help="JPEG quality (1-100)")
    p.add_argument("--no-masks", action="store_true",
                   help="leave out the instance masks and particle tables (what only the CNNs' d-value task needs)")
    p.add_argument("--shard-scenes", type=positive_int, default=PackSpec.shard_scenes, metavar="N",
                   help="scenes per shard at most (shards of a split are within one scene of each other)")
    p.add_argument("--seed", type=int, default=PackSpec.seed, metavar="N",
                   help="the seed of the order scenes are mixed in")
    p.add_argument("--jobs", type=positive_int, default=1, metavar="N", help="scenes encoded in parallel processes")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--out", metavar="DIR", help="the pack's folder (replaced as a whole)")
    what.add_argument("--verify", metavar="DIR", help="instead of packing, check a pack's shards against its "
                      "index (sizes and SHA-256, e.g. after a copy); exit status 1 when one is damaged or missing")
    p.set_defaults(func=cmd_pack)

    p = user("check-config", "It reads the file as a run does (the schema: every key, its type and range; the "
             "datasets; train.architectures) and prints one line: OK with the counts of datasets and scenes, or "
             "the file and what is wrong in it. The checks of the machine (the results folder is writable, the "
             "SLURM profile) come when a run starts.")
    p.add_argument("configfile", metavar="CONFIG",
                   help="a config YAML (config/*.yaml are examples; src/psdfactory/config.schema.yaml documents "
                        "every key)")
    p.set_defaults(func=cmd_check_config)

    # --- the workflow's steps ---
    for name in ("sample", "simulate", "render", "label"):
        p = workflow(name)
        p.add_argument("--params", required=True, metavar="JSON", help="the stage's config slice as JSON")
        p.add_argument("--skip-up-to-date", action="store_true",
                       help="skip scenes whose outputs are newer than their inputs and made with these params")
        p.add_argument("--jobs", type=int, default=1, metavar="N", help="scenes run in parallel processes")
        p.add_argument("--stamp", metavar="FILE", help="write a summary JSON here once every scene succeeded")
        p.add_argument("scene_dirs", nargs="+", metavar="SCENE_DIR",
                       help="scene folders (results/<dataset>/scenes/<scene id>)")
        p.set_defaults(func=cmd_stage)

    p = workflow("manifest")
    p.add_argument("--params", required=True, metavar="JSON", help='JSON with the "split" fractions, e.g. '
                   '{"split": {"train": 0.7, "val": 0.15, "test": 0.15}}')
    p.add_argument("--results", required=True, metavar="DIR", help="results root (image paths are relative to it)")
    p.add_argument("--scenes-out", required=True, metavar="FILE", help="the scene table shard to write (.parquet)")
    p.add_argument("--particles-out", required=True, metavar="FILE",
                   help="the particle table shard to write (.parquet)")
    p.add_argument("scene_dirs", nargs="*", metavar="SCENE_DIR", help="the shard's scene folders")
    p.set_defaults(func=cmd_manifest)

    p = workflow("ceiling")
    p.add_argument("--params", required=True, metavar="JSON", help='JSON: {"bounds": [a, b], "visible_min_px": 1}')
    p.add_argument("--dataset", required=True, metavar="NAME", help="the dataset the shards are of")
    p.add_argument("--scenes", nargs="+", required=True, metavar="PARQUET", help="the dataset's scene manifest shards")
    p.add_argument("--particles", nargs="+", required=True, metavar="PARQUET", help="its particle manifest shards")
    p.add_argument("--results", metavar="DIR", help="the results root the manifests' mask paths are relative to: "
                   "also compute the footprint ceiling (the instance read-out on the true masks)")
    p.add_argument("--reference-scenes", nargs="*", default=[], metavar="PARQUET",
                   help="a re-render's source dataset's scene shards: the read-outs are fitted on its scenes "
                   "of the splits in params' reference (the re-render's are too few to cross-validate)")
    p.add_argument("--reference-particles", nargs="*", default=[], metavar="PARQUET", help="its particle shards")
    p.add_argument("--out", required=True, metavar="FILE", help="the ceiling.json to write")
    p.set_defaults(func=cmd_ceiling)

    p = workflow("train", "A CNN can read its images from a pack (psdfactory pack) instead of the scene folders, and "
                 "train on several GPUs under torchrun, each process its own shards: torchrun --nproc-per-node 8 "
                 "-m psdfactory.cli train --pack DIR ... (docs/scale.md).")
    _job_args(p, "training settings as JSON (see learn.train.TrainParams)")
    _threads_arg(p, "the model's folder: model.pt, history.csv, TensorBoard logs")
    p.add_argument("--pack", metavar="DIR", help="a CNN: read the train and val scenes from this pack, packed at the "
                   "architecture's input size, instead of --results' scene folders (the only source under torchrun)")
    p.add_argument("--loader-workers", type=int, default=0, metavar="N",
                   help="with --pack: DataLoader worker processes decoding the shards, per training process")
    p.set_defaults(func=cmd_train)

    p = workflow("evaluate")
    _job_args(p, 'JSON: {"datasets": [...], "precision": "fp32"}', "the model.pt to evaluate")
    p.add_argument("--history", metavar="CSV", help="history.csv to plot the loss curves of")
    _threads_arg(p, "gets metrics.json, predictions.csv, scatter.png and loss_curve.png")
    p.set_defaults(func=cmd_evaluate)

    p = workflow("evaluate-photos", "Each photo is read at its mm per px and resized to the model's scale, as predict "
                 "does; the grains found are matched to the reference masks at the photo's resolution (IoU >= 0.5; "
                 "grains the border cuts left out) and the PSD compared with the reference d10/d50/d90.")
    p.add_argument("--params", required=True, metavar="JSON",
                   help='JSON: {"photoset": the config\'s photos.<name> with "name", "precision": "fp32"}')
    p.add_argument("--model", required=True, metavar="FILE", help="the model.pt to evaluate")
    _threads_arg(p, "gets metrics.json, photos.csv (a row per photo) and overlays/<photo>.png")
    p.set_defaults(func=cmd_evaluate_photos)

    p = workflow("benchmark")
    _job_args(p, 'JSON: {"dataset", "batch_size", "seconds", "repeats"}', "the model.pt to time")
    p.add_argument("--out", required=True, metavar="FILE", help="the benchmark's JSON to write")
    _threads_arg(p)
    p.set_defaults(func=cmd_benchmark)

    p = workflow("compare-backends")
    p.add_argument("--params", required=True, metavar="JSON", help="the render settings as JSON (cycles included)")
    p.add_argument("--results", required=True, metavar="DIR", help="the results root holding the dataset")
    p.add_argument("--dataset", required=True, metavar="NAME", help="the dataset whose scenes are rendered again")
    p.add_argument("-n", type=positive_int, default=3, metavar="N", help="number of scenes (at least 1)")
    p.add_argument("--out-dir", required=True, metavar="DIR", help="gets compare.png, compare.json and the renders")
    p.set_defaults(func=cmd_compare_backends)

    p = workflow("report")
    p.add_argument("--params", default="{}", metavar="JSON", help="the validated config as JSON")
    p.add_argument("--config-json", metavar="FILE", help="or: a file holding it (instead of --params)")
    each = "one per architecture, in the order of train.architectures"
    p.add_argument("--metrics", nargs="+", required=True, metavar="JSON", help=f"eval/<arch>/metrics.json, {each}")
    p.add_argument("--scatters", nargs="+", required=True, metavar="PNG", help=f"eval/<arch>/scatter.png, {each}")
    p.add_argument("--histories", nargs="+", required=True, metavar="CSV", help=f"models/<arch>/history.csv, {each}")
    p.add_argument("--bench", nargs="+", required=True, metavar="JSON", help=f"bench/<arch>.json, {each}")
    p.add_argument("--manifests", nargs="+", required=True, metavar="PARQUET",
                   help="the scene manifest shards of every dataset")
    p.add_argument("--contact-sheets", nargs="*", default=[], metavar="PNG",
                   help="<dataset>/contact_sheet.png, one per dataset in the config's order (or none)")
    p.add_argument("--ceilings", nargs="*", default=[], metavar="JSON",
                   help="<dataset>/ceiling.json, one per dataset in the config's order (or none)")
    p.add_argument("--photos", nargs="*", default=[], metavar="JSON",
                   help="eval/<arch>/photos/<set>/metrics.json, one per architecture and photo set (or none); "
                   "the overlays they name are read from overlays/ beside each")
    p.add_argument("--compare", nargs=2, metavar=("JSON", "PNG"),
                   help="the backend comparison's compare.json and compare.png")
    p.add_argument("--spread", metavar="JSON",
                   help="bench/seed_spread.py's spread.json, with each run's params.json beside it in "
                   "<seed>/<arch>/: each model's R² over training seeds (models of another recipe left out)")
    p.add_argument("--html", required=True, metavar="FILE", help="the report to write (.html)")
    p.add_argument("--md", required=True, metavar="FILE", help="its Markdown twin to write (.md)")
    p.set_defaults(func=cmd_report)
    ap.commands = sub.choices  # for _Parser.parse_args
    return ap


class _StderrHandler(logging.StreamHandler):
    """A handler that writes to whatever ``sys.stderr`` is when a record is emitted (a job's
    redirected log file, pytest's capture), not the one there was when it was made."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def configure_logging(verbosity: int = 0) -> None:
    """Send psdfactory's log records to stderr with time and level: INFO and up by default
    (progress and rate/ETA lines included), WARNING and up with ``verbosity < 0`` (--quiet),
    DEBUG with ``verbosity > 0`` (--verbose). Other libraries log WARNING and up. The rules
    redirect a job's stderr to its log file, so the job logs get every record. Idempotent."""
    root = logging.getLogger()
    if not any(isinstance(h, _StderrHandler) for h in root.handlers):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter(LOG_FORMAT, "%Y-%m-%d %H:%M:%S"))
        root.addHandler(handler)
    level = logging.WARNING if verbosity < 0 else logging.DEBUG if verbosity > 0 else logging.INFO
    logging.getLogger("psdfactory").setLevel(level)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    console = None
    if args.log:
        problem = log_problem(args)
        if problem:
            print(f"psdfactory {args.command}: error: {problem}", file=sys.stderr)
            return 2
        try:
            console = log_to(Path(args.log))
        except OSError as e:
            print(f"psdfactory {args.command}: error: cannot write the log {args.log}: "
                  f"{no_space(e) or e.strerror}", file=sys.stderr)
            return 2
    configure_logging(-1 if args.quiet else 1 if args.verbose else 0)
    logger.debug(f"psdfactory {__version__}, arguments {sys.argv[1:] if argv is None else argv}")
    try:
        return args.func(args) or 0
    except PsdError as e:  # the command's one-line verdict, shown whatever the log level
        return verdict(f"psdfactory {args.command}: error: {e}", console)
    except Exception as e:
        if isinstance(e, OSError) and no_space(e):  # a write not made through io.atomic_path
            return verdict(f"psdfactory {args.command}: error: {no_space(e)}", console)
        if console is None:
            raise
        return crashed(args, e, console)
    finally:
        if console is not None:
            os.close(console)


def log_to(path: Path) -> int:
    """Point this process's stdout and stderr (file descriptors 1 and 2, so C libraries' output
    too) at `path`, as the shell's ``> log 2>&1`` would, and return a descriptor of the stderr there
    was before: the console (Snakemake's, a SLURM job's output) that the verdict also goes to."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)  # the umask decides, as for every output
    sys.stdout.flush()
    sys.stderr.flush()
    console = os.dup(2)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    return console


def verdict(line: str, console: int | None, code: int = 2) -> int:
    """The command's last word: to stderr (the log with --log) and to the console, so it is seen
    even when the log cannot take it (its disk is full)."""
    try:
        print(line, file=sys.stderr, flush=True)
    except OSError:
        pass  # the log's disk is full; the console still gets it
    if console is not None:
        os.write(console, (line + "\n").encode())
    return code


def crashed(args: argparse.Namespace, e: BaseException, console: int) -> int:
    """An unexpected error under --log: the traceback to the log, one line naming it to the console."""
    try:
        traceback.print_exc(file=sys.stderr)
        sys.stderr.flush()
    except OSError:
        pass
    return verdict(f"psdfactory {args.command}: unexpected error: {type(e).__name__}: {e} "
                   f"(the traceback is in {args.log})", console, code=1)


def no_space(e: OSError) -> str | None:
    """The one-line message for a write that found its disk full (one not made through
    io.atomic_path, which says it itself: a log, predict's rows), or None for another error."""
    from .io import NO_SPACE, disk_full_message

    if e.errno not in NO_SPACE:
        return None
    return disk_full_message(e.filename or Path.cwd())


if __name__ == "__main__":
    sys.exit(main())
