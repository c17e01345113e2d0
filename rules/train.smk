rule train:
    input:
        manifests=train_manifests,
    output:
        model=f"{RESULTS}/models/{{arch}}/model.pt",
        history=f"{RESULTS}/models/{{arch}}/history.csv",
    log:
        f"{RESULTS}/models/{{arch}}/train.log",
    conda:
        "../envs/train.yaml"
    threads: all_cores
    params:
        stage=train_params,
        results=results_param,
        out_dir=lambda wildcards, output: os.path.dirname(output.model),
    shell:
        "psdfactory --log {log:q} train --params {params.stage:q} --results {params.results:q}"
        " --out-dir {params.out_dir:q} --threads {threads}"
