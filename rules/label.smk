rule label:
    input:
        spec=scene_path("spec.json"),
        geometry=scene_path("geometry.npz"),
        poses=scene_path("poses.parquet"),
        quality=scene_path("simulate.json"),
        mask=scene_path("mask.png"),
        meta=scene_path("render.json"),
    output:
        labels=scene_path("labels.json"),
        particles=scene_path("particles.parquet"),
    params:
        stage=label_params,
        scene_dir=lambda wildcards, input: os.path.dirname(input.spec),
    log:
        log_path("label"),
    conda:
        "../envs/scene.yaml"
    shell:
        "psdfactory label --params {params.stage:q} {params.scene_dir:q} > {log:q} 2>&1"
