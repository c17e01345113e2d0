rule sample:
    input:
        unpack(source_files("sample")),
    output:
        spec=scene_path("spec.json"),
        geometry=scene_path("geometry.npz"),
    log:
        log_path("sample"),
    conda:
        "../envs/scene.yaml"
    params:
        stage=sample_params,
        scene_dir=lambda wildcards, output: os.path.dirname(output.spec),
    shell:
        "psdfactory --log {log:q} sample --params {params.stage:q} {params.scene_dir:q}"


rule sample_batch:
    """Sample a batch of scenes (scenes_per_job > 1), skipping those up to date."""
    input:
        source_stamps("sample"),
    output:
        stamp=batch_stamp("sample"),
    log:
        batch_log("sample"),
    conda:
        "../envs/scene.yaml"
    threads: all_cores
    params:
        stage=sample_batch_params,
        scene_dirs=batch_scene_dirs,
    shell:
        "psdfactory --log {log:q} sample --params {params.stage:q} --skip-up-to-date --jobs {threads}"
        " --stamp {output.stamp:q} {params.scene_dirs:q}"
