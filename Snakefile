# psdfactory: synthetic particle-bed images with PSD labels.
#   snakemake -j2                          # the default config (config/config.yaml)
#   snakemake -j2 --configfile config/paper.yaml
# Per scene: sample -> simulate -> render -> label, one job each; then sharded Parquet manifests.

from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


include: "rules/common.smk"
include: "rules/sample.smk"
include: "rules/simulate.smk"
include: "rules/render.smk"
include: "rules/label.smk"
include: "rules/manifest.smk"


rule all:
    default_target: True
    input:
        all_targets(),
