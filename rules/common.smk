# Helpers shared by the rules: config validation, scene/shard enumeration and the resolved
# config slice of each stage (the rules' params, so rerun triggers fire only where an edit
# changes a stage's inputs).

import json
import os
import shutil
import sys

from snakemake.exceptions import WorkflowError

from psdfactory import PsdError
from psdfactory import config as psd_config
from psdfactory.seeding import scene_id, scene_index

try:
    psd_config.validate(config)  # Snakemake's own JSON-schema validation, defaults filled in
except PsdError as e:
    raise WorkflowError(str(e)) from None

# The jobs call the `psdfactory` CLI. When Snakemake runs from an unactivated virtualenv,
# use the one installed beside the Python that runs Snakemake.
if shutil.which("psdfactory") is None:
    shell.prefix(f"set -euo pipefail; export PATH={os.path.dirname(sys.executable)!r}:\"$PATH\"; ")

RESULTS = config["results"].rstrip("/")
DATASETS = list(config["datasets"])
ARCHS = list(config["train"]["architectures"])


wildcard_constraints:
    dataset="[A-Za-z][A-Za-z0-9_]*",
    scene="[A-Za-z][A-Za-z0-9_]*-[0-9]{6}",
    shard="[0-9]{5}",
    arch="[a-z][a-z0-9_]*",


def all_cores(wildcards):
    """Every core of a local run (so timing jobs run alone); on a cluster, where Snakemake has
    no core count, 8 unless the profile's set-threads says otherwise."""
    try:
        return workflow.cores
    except WorkflowError:
        return 8


def scene_path(name):
    """A file of a scene folder, as an output/input pattern."""
    return f"{RESULTS}/{{dataset}}/scenes/{{scene}}/{name}"


def log_path(stage):
    return f"{RESULTS}/{{dataset}}/logs/{stage}/{{scene}}.log"


def results_root(path, depth):
    """The results root above a file `depth` folders below it (for relative image paths)."""
    for _ in range(depth):
        path = os.path.dirname(path)
    return path or "."


def as_json(obj):
    return json.dumps(obj, sort_keys=True, separators=(",", ":"))


def sample_params(wildcards):
    return as_json(psd_config.sample_params(config, wildcards.dataset, scene_index(wildcards.scene)))


def simulate_params(wildcards):
    return as_json(psd_config.simulate_params(config))


def render_params(wildcards):
    return as_json(psd_config.render_params(config))


def label_params(wildcards):
    return as_json(psd_config.label_params(config))


def manifest_params(wildcards):
    return as_json(psd_config.manifest_params(config, wildcards.dataset))


def train_params(wildcards):
    return as_json(psd_config.train_params(config, wildcards.arch))


def evaluate_params(wildcards):
    return as_json({"datasets": DATASETS, "precision": config["evaluate"]["precision"], "arch": wildcards.arch})


def benchmark_params(wildcards):
    return as_json({"dataset": config["train"]["dataset"], **config["benchmark"]})


def shard_scene_files(name):
    """Input function: one file of every scene of a manifest shard."""

    def files(wildcards):
        rng = psd_config.shard_indices(config, wildcards.dataset, int(wildcards.shard))
        return [
            f"{RESULTS}/{wildcards.dataset}/scenes/{scene_id(wildcards.dataset, i)}/{name}"
            for i in rng
        ]

    return files


def shard_files(dataset, table):
    n = psd_config.n_shards(config, dataset)
    return [f"{RESULTS}/{dataset}/manifest/{table}/shard-{k:05d}.parquet" for k in range(n)]


def dataset_shards(table):
    return lambda wildcards: shard_files(wildcards.dataset, table)


SCENE_FILES = (
    "spec.json", "geometry.npz", "poses.parquet", "simulate.json",
    "image.png", "mask.png", "render.json", "labels.json", "particles.parquet",
)


def missing_scene_files(ds):
    """Files missing from scene folders that exist: deleted by hand, so name them as targets.

    Snakemake does not remake a missing intermediate file whose downstream outputs are up to
    date, so a deleted image would otherwise stay deleted. Only the missing ones are listed, so
    the target rule does not carry every file of every scene as an input.
    """
    missing = []
    for i in range(config["datasets"][ds]["n_scenes"]):
        d = f"{RESULTS}/{ds}/scenes/{scene_id(ds, i)}"
        if os.path.isdir(d):
            missing += [f"{d}/{f}" for f in SCENE_FILES if not os.path.exists(f"{d}/{f}")]
    return missing


def scene_targets():
    """Manifests and contact sheets of every dataset (+ any scene file deleted by hand)."""
    targets = []
    for ds in DATASETS:
        targets += shard_files(ds, "scenes") + shard_files(ds, "particles")
        targets.append(f"{RESULTS}/{ds}/contact_sheet.png")
        targets += missing_scene_files(ds)
    return targets


def all_targets():
    return scene_targets() + [f"{RESULTS}/report/report.html", f"{RESULTS}/report/report.md"]
