rule report:
    input:
        metrics=expand(f"{RESULTS}/eval/{{arch}}/metrics.json", arch=ARCHS),
        scatter=expand(f"{RESULTS}/eval/{{arch}}/scatter.png", arch=ARCHS),
        bench=expand(f"{RESULTS}/bench/{{arch}}.json", arch=ARCHS),
        histories=expand(f"{RESULTS}/models/{{arch}}/history.csv", arch=ARCHS),
        sheets=expand(f"{RESULTS}/{{dataset}}/contact_sheet.png", dataset=DATASETS),
        manifests=[f for ds in DATASETS for f in shard_files(ds, "scenes")],
    output:
        html=report(
            f"{RESULTS}/report/report.html",
            caption="../workflow/report/report.rst",
            category="Report",
        ),
        md=f"{RESULTS}/report/report.md",
    params:
        config=lambda wildcards: as_json(config),
        results=lambda wildcards, output: results_root(output.html, 2),
    log:
        f"{RESULTS}/report/report.log",
    conda:
        "../envs/train.yaml"
    shell:
        "psdfactory report --params {params.config:q} --results {params.results:q}"
        " --html {output.html:q} --md {output.md:q} > {log:q} 2>&1"
