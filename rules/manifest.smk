rule manifest_shard:
    input:
        unpack(shard_inputs),
    output:
        scenes=f"{RESULTS}/{{dataset}}/manifest/scenes/shard-{{shard}}.parquet",
        particles=f"{RESULTS}/{{dataset}}/manifest/particles/shard-{{shard}}.parquet",
    log:
        f"{RESULTS}/{{dataset}}/logs/manifest/shard-{{shard}}.log",
    conda:
        "../envs/scene.yaml"
    params:
        stage=manifest_params,
        results=results_param,
        scene_dirs=lambda wildcards, input: shard_scene_dirs(wildcards),
    shell:
        "psdfactory --log {log:q} manifest --params {params.stage:q} --results {params.results:q}"
        " --scenes-out {output.scenes:q} --particles-out {output.particles:q}"
        " {params.scene_dirs:q}"


rule contact_sheet:
    input:
        dataset_shards("scenes"),
    output:
        report(
            f"{RESULTS}/{{dataset}}/contact_sheet.png",
            caption="../workflow/report/contact_sheet.rst",
            category="Datasets",
            subcategory="{dataset}",
        ),
    log:
        f"{RESULTS}/{{dataset}}/logs/contact_sheet.log",
    conda:
        "../envs/scene.yaml"
    params:
        results=results_param,
        n=config["show"]["n_scenes"],
    shell:
        "psdfactory --log {log:q} show --results {params.results:q} --dataset {wildcards.dataset}"
        " -n {params.n} --out {output:q}"
