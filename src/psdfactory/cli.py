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
from .psd import SIZE_DEFINITIONS

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
    from .scene.show import contact_sheet

    if Path(a.out).is_dir():
        raise PsdError(f"--out {a.out} is a folder; give a .png file name")
    scenes = Path(a.results) / a.dataset / "scenes"
    if Path(a.out).resolve().is_relative_to(scenes.resolve()):
        raise PsdError(f"--out {a.out} is inside the scenes it shows ({scenes}); write the sheet elsewhere")
    if Path(a.out).suffix.lower() != ".png":
        raise PsdError(f"--out {a.out}: must end in .png")
    out = contact_sheet(Path(a.results), a.dataset, Path(a.out), a.n)
    logger.info(f"wrote {out}")


def cmd_compare_backends(a: argparse.Namespace) -> None:
    from .scene.show import compare_backends

    summary = compare_backends(Path(a.results), a.dataset, a.n, _params(a.params), Path(a.out_dir))
    for r in summary["scenes"]:
        logger.info(f"{r['scene_id']}: tiny {r['seconds_tiny']:.1f} s, cycles {r['seconds_cycles']:.1f} s, "
                    f"masks agree on {100 * r['mask_agreement']:.1f} % of pixels "
                    f"({100 * r['mask_agreement_off_edges']:.2f} % off edges)")


def cmd_check_config(a: argparse.Namespace) -> None:
    from .config import load_config
    from .preflight import check_architectures

    cfg = load_config(Path(a.configfile))
    try:
        check_architectures(cfg["train"]["architectures"])
    except PsdError as e:
        raise PsdError(f"{a.configfile}: invalid config: {e}") from None
    n = sum(d["n_scenes"] for d in cfg["datasets"].values())
    print(f"{a.configfile}: OK ({len(cfg['datasets'])} datasets, {n} scenes)")


def cmd_train(a: argparse.Namespace) -> None:
    from .learn.train import train_from_params

    _threads(a.threads)
    train_from_params(_params(a.params), Path(a.results), Path(a.out_dir))


def cmd_evaluate(a: argparse.Namespace) -> None:
    from .learn.evaluate import evaluate, plot_history

    p = _params(a.params)
    _threads(a.threads)
    out = Path(a.out_dir)
    evaluate(Path(a.model), Path(a.results), p["datasets"], out, precision=p.get("precision", "fp32"))
    if a.history:
        plot_history(Path(a.history), p.get("arch", Path(a.model).parent.name), out / "loss_curve.png")


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
             *(a.compare or []), *a.ceilings]
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
                                     a.contact_sheets, a.compare, a.ceilings)
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
            print(f"{r['image']:<50} " + " ".join(f"{r[t]:>8.3f}" for t in TARGETS), flush=True)

    out = Path(a.out) if a.out else None
    try:
        n, failed = stream_predictions(Path(a.model), a.images, out, a.mm_per_px, device=a.device, resume=a.resume,
                                       emit=emit, overlay_dir=Path(a.overlay) if a.overlay else None,
                                       masks_dir=Path(a.masks) if a.masks else None,
                                       particles_out=Path(a.particles) if a.particles else None,
                                       size_definition=a.size_definition)
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


def cmd_export(a: argparse.Namespace) -> None:
    from .deploy.export import export

    export(Path(a.model), Path(a.out_dir), int8_results=Path(a.int8) if a.int8 else None, dataset=a.dataset,
           max_r2_change=a.int8_max_r2_change)


def _threads(n: int) -> None:
    if n:
        import torch

        torch.set_num_threads(n)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="psdfactory", description=__doc__)
    ap.add_argument("--version", action="version", version=f"psdfactory {__version__}")
    loud = ap.add_mutually_exclusive_group()
    loud.add_argument("-q", "--quiet", action="store_true", help="log warnings and errors only (no progress bars)")
    loud.add_argument("-v", "--verbose", action="store_true", help="log debugging detail too")
    ap.add_argument("--log", metavar="FILE",
                    help="write everything the command prints (libraries' output too) to FILE, and its one-line "
                         "verdict on failure to stderr as well: the rules' job logs, which a full disk can swallow")
    sub = ap.add_subparsers(dest="command", required=True)

    for name, helptext in [
        ("sample", "draw a scene's particles → spec.json, geometry.npz"),
        ("simulate", "settle the particles with pybullet → poses.parquet, simulate.json"),
        ("render", "render the bed → image.png, mask.png, render.json"),
        ("label", "PSD labels → labels.json, particles.parquet"),
    ]:
        p = sub.add_parser(name, help=helptext)
        p.add_argument("--params", required=True, help="the stage's config slice as JSON")
        p.add_argument("--skip-up-to-date", action="store_true",
                       help="skip scenes whose outputs are newer than their inputs and made with these params")
        p.add_argument("--jobs", type=int, default=1, help="scenes run in parallel processes")
        p.add_argument("--stamp", help="write a summary JSON here once every scene succeeded")
        p.add_argument("scene_dirs", nargs="+", metavar="scene_dir")
        p.set_defaults(func=cmd_stage)

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
    p.add_argument("-n", type=positive_int, default=6, help="number of scenes (at least 1)")
    p.add_argument("--out", default="contact_sheet.png", help="the contact sheet, a .png file")
    p.set_defaults(func=cmd_show)

    p = sub.add_parser("train", help="train one architecture → model.pt, history.csv, TensorBoard logs")
    p.add_argument("--params", required=True, help="training settings as JSON (see learn.train.TrainParams)")
    p.add_argument("--results", required=True)
    p.add_argument("--out-dir", required=True)
    p.add_argument("--threads", type=int, default=0)
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("evaluate", help="metrics, predictions and plots of a trained model")
    p.add_argument("--params", required=True, help='JSON: {"datasets": [...], "precision": "fp32"}')
    p.add_argument("--model", required=True)
    p.add_argument("--results", required=True)
    p.add_argument("--out-dir", required=True)
    p.add_argument("--history", help="history.csv to plot the loss curves of")
    p.add_argument("--threads", type=int, default=0)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("benchmark", help="inference speed (fp32 eager vs the fast path) and accuracy change")
    p.add_argument("--params", required=True, help='JSON: {"dataset", "batch_size", "seconds", "repeats"}')
    p.add_argument("--model", required=True)
    p.add_argument("--results", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--threads", type=int, default=0)
    p.set_defaults(func=cmd_benchmark)

    p = sub.add_parser("ceiling", help="what a dataset's images allow: cross-validated R² ceilings per target")
    p.add_argument("--params", required=True, help='JSON: {"bounds": [a, b], "visible_min_px": 1}')
    p.add_argument("--dataset", required=True)
    p.add_argument("--scenes", nargs="+", required=True, metavar="PARQUET", help="the dataset's scene manifest shards")
    p.add_argument("--particles", nargs="+", required=True, metavar="PARQUET", help="its particle manifest shards")
    p.add_argument("--results", help="the results root the manifests' mask paths are relative to: also compute the "
                   "footprint ceiling (the instance read-out on the true masks)")
    p.add_argument("--reference-scenes", nargs="*", default=[], metavar="PARQUET",
                   help="a re-render's source dataset's scene shards: the read-outs are fitted on its scenes "
                   "of the splits in params' reference (the re-render's are too few to cross-validate)")
    p.add_argument("--reference-particles", nargs="*", default=[], metavar="PARQUET", help="its particle shards")
    p.add_argument("--out", required=True, help="ceiling.json")
    p.set_defaults(func=cmd_ceiling)

    p = sub.add_parser("report", help="the final HTML report and its Markdown twin")
    p.add_argument("--params", default="{}", help="the validated config as JSON")
    p.add_argument("--config-json", help="or: a file holding it")
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
    p.add_argument("--compare", nargs=2, metavar=("JSON", "PNG"),
                   help="the backend comparison's compare.json and compare.png")
    p.add_argument("--html", required=True)
    p.add_argument("--md", required=True)
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("predict", help="d10/d50/d90 in mm for image files or folders")
    p.add_argument("--model", required=True, help="a model.pt written by training, or an exported .onnx (fp32 or int8)")
    p.add_argument("--mm-per-px", type=mm_per_px_arg, metavar="MM",
                   help="scale of the images in mm per pixel (1e-4 to 1e3); they are rescaled to the model's scale")
    p.add_argument("--out", help="write the predictions to this .csv or .json file (rows go to <out>.partial.csv as "
                   "they come; it becomes <out> when every image is done)")
    p.add_argument("--resume", action="store_true",
                   help="skip the images that already have a prediction in --out or its .partial.csv "
                        "(failed ones are retried)")
    p.add_argument("--device", default="cpu", help="cpu (default), auto, cuda or cuda:N")
    p.add_argument("--overlay", metavar="DIR", help="instance models: write each image with its particles' outlines "
                   "and sizes (mm) drawn on as DIR/<image stem>.png")
    p.add_argument("--masks", metavar="DIR", help="instance models: write each image's instance mask as "
                   "DIR/<image stem>.png (16-bit, 0 = background, k = one particle)")
    p.add_argument("--particles", metavar="FILE", help="instance models: write every measured particle to this CSV "
                   "(image, id, area_mm2, sieve_size_mm, volume_mm3, touches_edge)")
    p.add_argument("--size-definition", choices=SIZE_DEFINITIONS, metavar="NAME",
                   help="what d10/d50/d90 are of: " + ", ".join(SIZE_DEFINITIONS) + " (default: the definition "
                   "the model was trained on, in the CSV's size_definition column). An instance model also "
                   "estimates the other solid definitions (sieve, b-axis, c-axis, esd) and measures feret-min, "
                   "feret-max and ecd on the whole grains it finds; a CNN reads only its own")
    p.add_argument("images", nargs="+", help="image files and/or folders of images")
    p.set_defaults(func=cmd_predict)

    p = sub.add_parser("export",
                       help="write the model as ONNX and TorchScript (and int8 ONNX), checked against PyTorch")
    p.add_argument("--model", required=True)
    p.add_argument("--out-dir", required=True)
    p.add_argument("--int8", metavar="RESULTS",
                   help="also model.int8.onnx, calibrated on this results root's training images")
    p.add_argument("--dataset", default="train", help="dataset to calibrate and check int8 on")
    p.add_argument("--int8-max-r2-change", type=float, default=None,
                   help="refuse the int8 model if its overall R² on the test split moves more than this "
                        "(default: the benchmark's accuracy budget)")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("compare-backends", help="render a few scenes with both backends, side by side")
    p.add_argument("--params", required=True, help="the render settings as JSON (cycles included)")
    p.add_argument("--results", required=True)
    p.add_argument("--dataset", required=True)
    p.add_argument("-n", type=positive_int, default=3, help="number of scenes (at least 1)")
    p.add_argument("--out-dir", required=True, help="gets compare.png, compare.json and the renders")
    p.set_defaults(func=cmd_compare_backends)

    p = sub.add_parser("check-config", help="validate a config file against the schema")
    p.add_argument("configfile")
    p.set_defaults(func=cmd_check_config)
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
