rule sample:
    output:
        spec=scene_path("spec.json"),
        geometry=scene_path("geometry.npz"),
    params:
        stage=sample_params,
        scene_dir=lambda wildcards, output: os.path.dirname(output.spec),
    log:
        log_path("sample"),
    conda:
        "../envs/scene.yaml"
    shell:
        "psdfactory sample --params {params.stage:q} {params.scene_dir:q} > {log:q} 2>&1"
