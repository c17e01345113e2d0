rule simulate:
    input:
        spec=scene_path("spec.json"),
        geometry=scene_path("geometry.npz"),
    output:
        poses=scene_path("poses.parquet"),
        quality=scene_path("simulate.json"),
    params:
        stage=simulate_params,
        scene_dir=lambda wildcards, input: os.path.dirname(input.spec),
    log:
        log_path("simulate"),
    conda:
        "../envs/scene.yaml"
    shell:
        "psdfactory simulate --params {params.stage:q} {params.scene_dir:q} > {log:q} 2>&1"
