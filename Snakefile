# psdfactory: synthetic particle-bed images with PSD labels.
#   snakemake -j2                          # the default config (config/config.yaml)
#   snakemake -j2 --configfile config/paper.yaml
# Per scene: sample -> simulate -> render -> label, one job each (or, with scenes_per_job: N, one
# job per batch of N scenes that skips the scenes already up to date); then sharded Parquet
# manifests, one training job per architecture, evaluation, an inference benchmark and one final
# report (with a few scenes rendered by both render backends).

from snakemake.utils import min_version

min_version("9.0")


# The default config, unless --configfile names another: Snakemake would otherwise merge the
# two, and a user's config would silently inherit the default's datasets.
if not workflow.overwrite_configfiles:

    configfile: "config/config.yaml"


include: "rules/common.smk"
include: "rules/sample.smk"
include: "rules/simulate.smk"
include: "rules/render.smk"
include: "rules/label.smk"
include: "rules/manifest.smk"
include: "rules/train.smk"
include: "rules/evaluate.smk"
include: "rules/photos.smk"
include: "rules/benchmark.smk"
include: "rules/report.smk"


rule all:
    default_target: True
    input:
        all_targets(),


rule scenes:
    """Only the datasets: every scene, the manifests and the contact sheets (no training)."""
    input:
        scene_targets(),
