# Helpers shared by the rules: config validation, scene/shard enumeration and the resolved
# config slice of each stage (the rules' params, so rerun triggers fire only where an edit
# changes a stage's inputs).

import getpass
import json
import os
import shutil
import sys

from snakemake.exceptions import WorkflowError

from psdfactory import PsdError
from psdfactory import config as psd_config
from psdfactory import photoset as psd_photoset
from psdfactory import preflight as psd_preflight
from psdfactory import runlock as psd_runlock
from psdfactory.learn.registry import check_architectures
from psdfactory.manifest import shard_name
from psdfactory.report import SPREAD_JSON
from psdfactory.scene import stages as psd_stages
from psdfactory.scene.stages import STAGES
from psdfactory.seeding import scene_id, scene_index

# Validated against the package's schema, src/psdfactory/config.schema.yaml (psd_config.SCHEMA): the
# one schema file, which `psdfactory check-config` reads too.
try:
    for _f in workflow.configfiles:  # read again strictly: UTF-8, no key twice, no alias bomb
        psd_config.read_yaml(_f)
except PsdError as e:  # the message names the file
    raise WorkflowError(str(e)) from None
try:
    psd_config.validate(config)  # Snakemake's own JSON-schema validation, defaults filled in
except PsdError as e:  # the message names the key; say which file(s) it came from (or --config)
    raise WorkflowError(f"{', '.join(map(str, workflow.configfiles)) or 'the config'}: {e}") from None

# The jobs call the `psdfactory` CLI. When Snakemake runs from an unactivated virtualenv,
# use the one installed beside the Python that runs Snakemake.
if shutil.which("psdfactory") is None:
    shell.prefix(f'set -euo pipefail; export PATH={os.path.dirname(sys.executable)!r}:"$PATH"; ')

RESULTS = config["results"].rstrip("/")  # every job that needs the results root gets it as --results
DATASETS = list(config["datasets"])
EVALUATED = psd_config.evaluation_datasets(config)  # every model is scored on these
ARCHS = list(config["train"]["architectures"])
PHOTOS = list(config["photos"])  # photo sets: labelled photographs every model is evaluated on


# ---- fail fast: what would otherwise fail hours later (or hang) inside a job ------------------


def profile_resources():
    """The resources the profile and the command line set (default-resources, set-resources),
    as their raw values: {"default-resources": {key: value}, "set-resources <rule>": {...}}."""
    rs = workflow.resource_settings
    raw = lambda values: {k: getattr(v, "raw", v) for k, v in values.items()}
    found = {"default-resources": raw(rs.default_resources)} if rs.default_resources is not None else {}
    for rule, values in (rs.overwrite_resources or {}).items():
        found[f"set-resources {rule}"] = raw(values)
    return found


def require_blender(what):
    """[] if Blender's Python is there; otherwise a WorkflowError saying how to install it."""
    from psdfactory.scene.render.cycles import blender_python

    try:
        blender_python()
    except PsdError as e:
        raise WorkflowError(f"psdfactory: {what} — {e}") from None
    return []


def compare_inputs(wildcards):
    """The training dataset's scene shards, for the report's backend comparison. Blender is
    checked here, as the DAG is built, so only where the comparison is part of it (the default
    target, not `scenes`): a missing Blender stops the run before any job starts."""
    require_blender("show.compare_backends > 0 (the report compares tiny and cycles renders; 0 turns it off)")
    return shard_files(psd_config.main_training_dataset(config), "scenes")


def preflight():
    """The results folder is writable; the SLURM profile's account and partitions are set and
    known (sinfo/sacctmgr, where they answer); Blender is there for datasets rendered by
    Cycles. Looks only, changes nothing: a dry run checks the same."""
    try:
        psd_preflight.check_results(RESULTS)
        check_architectures(config["train"]["architectures"])
        psd_photoset.check(config)  # the photo sets' files: there, readable, each photo with its scale
        psd_preflight.check_slurm(profile_resources(), os.environ, getpass.getuser())
    except PsdError as e:
        raise WorkflowError(f"psdfactory: {e}") from None
    cycles = [ds for ds in DATASETS if psd_config.dataset_render(config, ds)["backend"] == "cycles"]
    if cycles:
        plural = len(cycles) > 1
        require_blender(f"dataset{'s' * plural} {', '.join(cycles)} render{'' if plural else 's'} with Cycles")


# Once, in the process the user started: not in the jobs Snakemake starts (they re-parse this
# file), nor in --lint (which, like Snakemake's own envvars check, does not look at the machine).
if workflow.is_main_process and workflow.check_envvars:
    preflight()


RESULTS_LOCK = []  # the results folder's lock (an open file), held while this process runs jobs


def lock_results():
    """One run per results folder (psdfactory.runlock). Taken when jobs start, in the process
    the user started: not in a dry run (Snakemake runs no onstart there), nor in the jobs it
    starts; released when this process ends, however it ends (kill -9 included)."""
    if not workflow.is_main_process:
        return
    try:
        RESULTS_LOCK.append(psd_runlock.lock_results(RESULTS))
    except PsdError as e:
        raise WorkflowError(f"psdfactory: {e}") from None


onstart:
    lock_results()


wildcard_constraints:
    dataset="[A-Za-z][A-Za-z0-9_]*",
    scene="[A-Za-z][A-Za-z0-9_]*-[0-9]{6}",
    shard="[0-9]{5}",
    batch="[0-9]{5}",
    arch="[a-z][a-z0-9_]*",
    photoset="[A-Za-z][A-Za-z0-9_]*",


def all_cores(wildcards):
    """Every core of a local run (so timing jobs run alone); on a cluster, where Snakemake has
    no core count, 8 unless the profile's set-threads says otherwise."""
    try:
        return workflow.cores
    except WorkflowError:
        return 8


def render_gpus(wildcards):
    """The Cycles backend renders on a GPU where there is one (SLURM: `gpu` → --gpus)."""
    r = psd_config.dataset_render(config, wildcards.dataset)
    return int(r["backend"] == "cycles" and r["cycles"]["device"] != "cpu")


def scene_path(name):
    """A file of a scene folder, as an output/input pattern."""
    return f"{RESULTS}/{{dataset}}/scenes/{{scene}}/{name}"


def log_path(stage):
    return f"{RESULTS}/{{dataset}}/logs/{stage}/{{scene}}.log"


def results_param(wildcards, output):
    """The results root, for a job's --results. A location, not a setting: every output path
    already starts with it, so the function takes `output` and Snakemake counts the param as
    derived from the outputs and leaves it out of its params rerun trigger (a changed root
    means other output paths anyway)."""
    return RESULTS


def as_json(obj):
    return json.dumps(obj, sort_keys=True, separators=(",", ":"))


def sample_params(wildcards):
    return as_json(psd_config.sample_params(config, wildcards.dataset, scene_index(wildcards.scene)))


def sample_batch_params(wildcards):
    return as_json(psd_config.sample_params(config, wildcards.dataset))


def simulate_params(wildcards):
    return as_json(psd_config.simulate_params(config, wildcards.dataset))


def render_params(wildcards):
    return as_json(psd_config.render_params(config, wildcards.dataset))


def label_params(wildcards):
    return as_json(psd_config.label_params(config, wildcards.dataset))


def ceiling_params(wildcards):
    return as_json(psd_config.ceiling_params(config, wildcards.dataset))


def manifest_params(wildcards):
    return as_json(psd_config.manifest_params(config, wildcards.dataset))


def train_params(wildcards):
    return as_json(psd_config.train_params(config, wildcards.arch))


def train_manifests(wildcards):
    """The scene manifests of the datasets this architecture trains on (train.datasets, or its own)."""
    return shards_of(psd_config.train_params(config, wildcards.arch)["datasets"], "scenes")


def evaluate_params(wildcards):
    return as_json(
        {
            "datasets": EVALUATED,
            "precision": config["evaluate"]["precision"],
            "arch": wildcards.arch,
        }
    )


def photo_params(wildcards):
    return as_json(
        {
            "photoset": psd_config.photo_params(config, wildcards.photoset),
            "precision": config["evaluate"]["precision"],
        }
    )


def photo_set(wildcards):
    """The photo set of a job (psdfactory.photoset: its photos, masks and tables, checked)."""
    try:
        return psd_photoset.resolve(wildcards.photoset, config["photos"][wildcards.photoset])
    except PsdError as e:
        raise WorkflowError(f"psdfactory: {e}") from None


def photo_files(wildcards):
    """A photo set's files (photos, masks, CSVs): its evaluation's inputs."""
    return [str(f) for f in photo_set(wildcards).files()]


def photo_threads(wildcards):
    """A photo set's evaluation: a thread per photo, up to every core (a job of a few photos is mostly
    PyTorch's start, and runs beside another)."""
    return max(1, min(all_cores(wildcards), len(photo_set(wildcards).photos)))


def photo_targets(name):
    """Every model's evaluation on the photo sets: eval/<arch>/photos/<set>/`name`."""
    return expand(f"{RESULTS}/eval/{{arch}}/photos/{{photoset}}/{name}", arch=ARCHS, photoset=PHOTOS)


def benchmark_params(wildcards):
    return as_json({"dataset": psd_config.main_training_dataset(config), **config["benchmark"]})


# ---- scene batches (scenes_per_job > 1) ----------------------------------------------------
# A batch job runs one stage over N scenes and skips those already up to date (per scene:
# outputs newer than inputs, same params); its stamp lists the scenes. Rerun triggers work on
# the stamps: a changed stage slice or scene list reruns the batch, a newer upstream stamp
# reruns the batch after it, and within a batch only the scenes that changed are regenerated.

BATCHED = config["scenes_per_job"] > 1


def batch_stamp(stage):
    return f"{RESULTS}/{{dataset}}/batches/{stage}/batch-{{batch}}.json"


def batch_stamp_of(dataset, stage, batch):
    """The stamp of one batch (batch_stamp with its wildcards filled in)."""
    return batch_stamp(stage).format(dataset=dataset, batch=f"{batch:05d}")


def batch_log(stage):
    return f"{RESULTS}/{{dataset}}/logs/{stage}/batch-{{batch}}.log"


def scene_dirs(dataset, indices):
    return [f"{RESULTS}/{dataset}/scenes/{scene_id(dataset, i)}" for i in indices]


def batch_scene_dirs(wildcards):
    return scene_dirs(wildcards.dataset, psd_config.batch_indices(config, wildcards.dataset, int(wildcards.batch)))


# ---- re-render datasets: the scenes of another dataset, rendered again --------------------


def source_scenes(dataset, indices):
    """(source dataset, its scene indices) of these scenes of a re-render dataset; None for a
    dataset that makes its own scenes."""
    if "rerender_of" not in config["datasets"][dataset]:
        return None
    src = psd_config.source_indices(config, dataset)
    return config["datasets"][dataset]["rerender_of"]["dataset"], [src[i] for i in indices]


def source_files(stage):
    """Input function: the source scene's files that a re-rendered scene's `stage` copies."""

    def inputs(wildcards):
        found = source_scenes(wildcards.dataset, [scene_index(wildcards.scene)])
        if found is None:
            return {}
        d = scene_dirs(found[0], found[1])[0]
        return {f"source_{f.split('.')[0]}": f"{d}/{f}" for f in STAGES[stage].outputs}

    return inputs


def source_stamps(stage):
    """Input function of a batch job: the source batches' stamps of `stage` (re-render only)."""

    def inputs(wildcards):
        found = source_scenes(
            wildcards.dataset, psd_config.batch_indices(config, wildcards.dataset, int(wildcards.batch))
        )
        if found is None:
            return []
        batches = sorted({i // config["scenes_per_job"] for i in found[1]})
        return [batch_stamp_of(found[0], stage, b) for b in batches]

    return inputs


def shard_scene_dirs(wildcards):
    return scene_dirs(wildcards.dataset, psd_config.shard_indices(config, wildcards.dataset, int(wildcards.shard)))


def shard_inputs(wildcards):
    """Inputs of a manifest shard: the labels, particles and image of each of its scenes (one
    job per scene), or the label stamps of the batches that hold them (scenes_per_job > 1)."""
    if BATCHED:
        batches = psd_config.shard_batches(config, wildcards.dataset, int(wildcards.shard))
        return {"stamps": [batch_stamp_of(wildcards.dataset, "label", b) for b in batches]}
    dirs = shard_scene_dirs(wildcards)
    return {
        name: [f"{d}/{name}.{ext}" for d in dirs]
        for name, ext in (("labels", "json"), ("particles", "parquet"), ("image", "png"))
    }


def shard_files(dataset, table):
    n = psd_config.n_shards(config, dataset)
    return [f"{RESULTS}/{dataset}/manifest/{table}/{shard_name(k)}" for k in range(n)]


def shards_of(datasets, table):
    """The manifest shards (`scenes` or `particles`) of several datasets."""
    return [f for ds in datasets for f in shard_files(ds, table)]


def dataset_shards(table):
    return lambda wildcards: shard_files(wildcards.dataset, table)


def ceiling_reference_shards(table):
    """A re-render's source dataset's shards, where its ceilings fit their read-outs ([] else)."""

    def shards(wildcards):
        ref = psd_config.ceiling_reference(config, wildcards.dataset)
        return shard_files(ref["dataset"], table) if ref else []

    return shards


def missing_scene_files(ds):
    """Files missing from scene folders that exist: deleted by hand, so name them as targets.

    Snakemake does not remake a missing intermediate file whose downstream outputs are up to
    date, so a deleted image would otherwise stay deleted. Naming it as a target makes the scene's
    own stage rule (`render` for an image — in batch mode too) regenerate it, identical, and
    nothing else: no file is removed to force a rerun, so a dry run changes nothing. Only the
    main process looks (the jobs Snakemake starts re-parse this file and need no targets): one
    directory listing per scene folder, once per invocation.
    """
    if not workflow.is_main_process:
        return []
    ids = [scene_id(ds, i) for i in range(config["datasets"][ds]["n_scenes"])]
    missing = psd_stages.missing_scene_files(f"{RESULTS}/{ds}/scenes", ids)
    for f in missing:
        print(f"psdfactory: {f} is missing; its stage will regenerate it", file=sys.stderr)
    return missing


def scene_targets():
    """Manifests and contact sheets of every dataset (+ any scene file deleted by hand)."""
    targets = []
    for ds in DATASETS:
        targets += shard_files(ds, "scenes") + shard_files(ds, "particles")
        targets.append(f"{RESULTS}/{ds}/contact_sheet.png")
        targets += missing_scene_files(ds)
    return targets


def compare_targets():
    """The report's side-by-side renders of both backends (show.compare_backends scenes):
    [compare.json, compare.png], the order `psdfactory report --compare` takes them in."""
    if config["show"]["compare_backends"] == 0:
        return []
    return [f"{RESULTS}/report/backends/compare.json", f"{RESULTS}/report/backends/compare.png"]


def seed_spread_input():
    """bench/seed_spread.py's spread.json under the results, where one has been measured (it is made
    outside the DAG): the report shows each model's R² over its training seeds."""
    path = f"{RESULTS}/{SPREAD_JSON.as_posix()}"
    return [path] if os.path.exists(path) else []


def all_targets():
    return scene_targets() + [f"{RESULTS}/report/report.html", f"{RESULTS}/report/report.md"]
