rule report:
    input:
        metrics=expand(f"{RESULTS}/eval/{{arch}}/metrics.json", arch=ARCHS),
        scatter=expand(f"{RESULTS}/eval/{{arch}}/scatter.png", arch=ARCHS),
        bench=expand(f"{RESULTS}/bench/{{arch}}.json", arch=ARCHS),
        histories=expand(f"{RESULTS}/models/{{arch}}/history.csv", arch=ARCHS),
        sheets=expand(f"{RESULTS}/{{dataset}}/contact_sheet.png", dataset=DATASETS),
        ceilings=expand(f"{RESULTS}/{{dataset}}/ceiling.json", dataset=DATASETS),
        manifests=shards_of(DATASETS, "scenes"),
        backends=compare_targets(),
        photos=photo_targets("metrics.json"),
        overlays=photo_targets("overlays"),  # the figures each photos' metrics.json names
        spread=seed_spread_input(),  # over training seeds, where bench/seed_spread.py measured them
    output:
        html=report(
            f"{RESULTS}/report/report.html",
            caption="../workflow/report/report.rst",
            category="Report",
        ),
        md=f"{RESULTS}/report/report.md",
    log:
        f"{RESULTS}/report/report.log",
    conda:
        "../envs/train.yaml"
    params:
        config=lambda wildcards: as_json(config),
        compare=lambda wildcards, input: ["--compare", *input.backends] if input.backends else [],
        spread=lambda wildcards, input: ["--spread", *input.spread] if input.spread else [],
    shell:
        "psdfactory --log {log:q} report --params {params.config:q} --metrics {input.metrics:q} --scatters {input.scatter:q}"
        " --histories {input.histories:q} --bench {input.bench:q} --manifests {input.manifests:q}"
        " --contact-sheets {input.sheets:q} --ceilings {input.ceilings:q} {params.compare:q} {params.spread:q} --photos {input.photos:q}"
        " --html {output.html:q} --md {output.md:q}"


rule compare_backends:
    """A few scenes rendered by both backends from the same poses, for the report."""
    input:
        compare_inputs,  # checks Blender
    output:
        figure=report(
            f"{RESULTS}/report/backends/compare.png",
            caption="../workflow/report/compare_backends.rst",
            category="Datasets",
        ),
        summary=f"{RESULTS}/report/backends/compare.json",
    log:
        f"{RESULTS}/report/backends/compare.log",
    conda:
        "../envs/scene.yaml"
    params:
        stage=lambda wildcards: as_json(psd_config.compare_params(config)),
        dataset=psd_config.main_training_dataset(config),
        n=config["show"]["compare_backends"],
        results=results_param,
        out_dir=lambda wildcards, output: os.path.dirname(output.figure),
    shell:
        "psdfactory --log {log:q} compare-backends --params {params.stage:q} --results {params.results:q}"
        " --dataset {params.dataset} -n {params.n} --out-dir {params.out_dir:q}"
