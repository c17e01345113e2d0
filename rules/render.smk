rule render:
    input:
        spec=scene_path("spec.json"),
        geometry=scene_path("geometry.npz"),
        poses=scene_path("poses.parquet"),
    output:
        image=scene_path("image.png"),
        mask=scene_path("mask.png"),
        meta=scene_path("render.json"),
    params:
        stage=render_params,
        scene_dir=lambda wildcards, input: os.path.dirname(input.spec),
    log:
        log_path("render"),
    conda:
        "../envs/scene.yaml"
    shell:
        "psdfactory render --params {params.stage:q} {params.scene_dir:q} > {log:q} 2>&1"
