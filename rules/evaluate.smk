rule evaluate:
    input:
        model=f"{RESULTS}/models/{{arch}}/model.pt",
        history=f"{RESULTS}/models/{{arch}}/history.csv",
        manifests=shards_of(EVALUATED, "scenes"),
        # an estimator's scorer may read them (the instance estimator scores each matched grain's size)
        particles=shards_of(EVALUATED, "particles"),
    output:
        metrics=f"{RESULTS}/eval/{{arch}}/metrics.json",
        predictions=f"{RESULTS}/eval/{{arch}}/predictions.csv",
        scatter=report(
            f"{RESULTS}/eval/{{arch}}/scatter.png",
            caption="../workflow/report/scatter.rst",
            category="Accuracy",
            subcategory="{arch}",
        ),
        curve=report(
            f"{RESULTS}/eval/{{arch}}/loss_curve.png",
            caption="../workflow/report/loss_curve.rst",
            category="Training",
            subcategory="{arch}",
        ),
    log:
        f"{RESULTS}/eval/{{arch}}/evaluate.log",
    conda:
        "../envs/train.yaml"
    threads: all_cores
    params:
        stage=evaluate_params,
        results=results_param,
        out_dir=lambda wildcards, output: os.path.dirname(output.metrics),
    shell:
        "psdfactory --log {log:q} evaluate --params {params.stage:q} --model {input.model:q} --results {params.results:q}"
        " --out-dir {params.out_dir:q} --history {input.history:q} --threads {threads}"


rule ceiling:
    """What the dataset's images allow: labels read out from the true sizes of the visible
    particles, from the footprints of the true masks (and from the generator's own
    distribution), cross-validated, per target (a re-render's: fitted on its source's other
    scenes)."""
    input:
        scenes=dataset_shards("scenes"),
        particles=dataset_shards("particles"),
        reference_scenes=ceiling_reference_shards("scenes"),
        reference_particles=ceiling_reference_shards("particles"),
    output:
        f"{RESULTS}/{{dataset}}/ceiling.json",
    log:
        f"{RESULTS}/{{dataset}}/logs/ceiling.log",
    conda:
        "../envs/scene.yaml"
    params:
        stage=ceiling_params,
        results=results_param,
    shell:
        "psdfactory --log {log:q} ceiling --params {params.stage:q} --dataset {wildcards.dataset} --scenes {input.scenes:q}"
        " --particles {input.particles:q} --reference-scenes {input.reference_scenes:q}"
        " --reference-particles {input.reference_particles:q} --results {params.results:q} --out {output:q}"
