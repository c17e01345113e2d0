rule simulate:
    input:
        unpack(source_files("simulate")),
        spec=scene_path("spec.json"),
        geometry=scene_path("geometry.npz"),
    output:
        poses=scene_path("poses.parquet"),
        quality=scene_path("simulate.json"),
    log:
        log_path("simulate"),
    conda:
        "../envs/scene.yaml"
    params:
        stage=simulate_params,
        scene_dir=lambda wildcards, input: os.path.dirname(input.spec),
    shell:
        "psdfactory --log {log:q} simulate --params {params.stage:q} {params.scene_dir:q}"


rule simulate_batch:
    """Simulate a batch of scenes (scenes_per_job > 1), skipping those up to date."""
    input:
        batch_stamp("sample"),
        source_stamps("simulate"),
    output:
        stamp=batch_stamp("simulate"),
    log:
        batch_log("simulate"),
    conda:
        "../envs/scene.yaml"
    threads: all_cores
    params:
        stage=simulate_params,
        scene_dirs=batch_scene_dirs,
    shell:
        "psdfactory --log {log:q} simulate --params {params.stage:q} --skip-up-to-date --jobs {threads}"
        " --stamp {output.stamp:q} {params.scene_dirs:q}"
