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
    log:
        log_path("label"),
    conda:
        "../envs/scene.yaml"
    params:
        stage=label_params,
        scene_dir=lambda wildcards, input: os.path.dirname(input.spec),
    shell:
        "psdfactory --log {log:q} label --params {params.stage:q} {params.scene_dir:q}"


rule label_batch:
    """Label a batch of scenes (scenes_per_job > 1), skipping those up to date."""
    input:
        batch_stamp("render"),
    output:
        stamp=batch_stamp("label"),
    log:
        batch_log("label"),
    conda:
        "../envs/scene.yaml"
    threads: all_cores
    params:
        stage=label_params,
        scene_dirs=batch_scene_dirs,
    shell:
        "psdfactory --log {log:q} label --params {params.stage:q} --skip-up-to-date --jobs {threads}"
        " --stamp {output.stamp:q} {params.scene_dirs:q}"
