rule render:
    input:
        spec=scene_path("spec.json"),
        geometry=scene_path("geometry.npz"),
        poses=scene_path("poses.parquet"),
    output:
        image=scene_path("image.png"),
        mask=scene_path("mask.png"),
        meta=scene_path("render.json"),
    log:
        log_path("render"),
    conda:
        "../envs/scene.yaml"
    resources:
        gpu=render_gpus,
    params:
        stage=render_params,
        scene_dir=lambda wildcards, input: os.path.dirname(input.spec),
    shell:
        "psdfactory --log {log:q} render --params {params.stage:q} {params.scene_dir:q}"


rule render_batch:
    """Render a batch of scenes (scenes_per_job > 1), skipping those up to date."""
    input:
        batch_stamp("simulate"),
    output:
        stamp=batch_stamp("render"),
    log:
        batch_log("render"),
    conda:
        "../envs/scene.yaml"
    threads: all_cores
    resources:
        gpu=render_gpus,
    params:
        stage=render_params,
        scene_dirs=batch_scene_dirs,
    shell:
        "psdfactory --log {log:q} render --params {params.stage:q} --skip-up-to-date --jobs {threads}"
        " --stamp {output.stamp:q} {params.scene_dirs:q}"
