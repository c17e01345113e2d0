# Timings need the machine to themselves: the rule asks for every core, so locally it never
# shares the CPU with another job.
rule benchmark:
    input:
        model=f"{RESULTS}/models/{{arch}}/model.pt",
        manifests=lambda wildcards: shard_files(psd_config.main_training_dataset(config), "scenes"),
    output:
        f"{RESULTS}/bench/{{arch}}.json",
    log:
        f"{RESULTS}/bench/{{arch}}.log",
    conda:
        "../envs/train.yaml"
    threads: all_cores
    params:
        stage=benchmark_params,
        results=results_param,
    shell:
        "psdfactory --log {log:q} benchmark --params {params.stage:q} --model {input.model:q} --results {params.results:q}"
        " --out {output:q} --threads {threads}"
