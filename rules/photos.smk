# Photo sets (config `photos`): labelled photographs brought from outside, nothing generated for
# them. Every model is evaluated on each, as on the synthetic test splits (deploy/photos.py).


rule evaluate_photos:
    """One model on one photo set: the grains it finds against the reference masks (P/R/F1 at
    IoU 0.5, matched grains' size error) and its PSD against the reference d10/d50/d90."""
    input:
        model=f"{RESULTS}/models/{{arch}}/model.pt",
        photos=photo_files,
    output:
        metrics=f"{RESULTS}/eval/{{arch}}/photos/{{photoset}}/metrics.json",
        table=report(
            f"{RESULTS}/eval/{{arch}}/photos/{{photoset}}/photos.csv",
            caption="../workflow/report/photos_table.rst",
            category="Photos",
            subcategory="{photoset}",
            labels={"model": "{arch}", "figure": "per-photo table"},
        ),
        overlays=report(
            directory(f"{RESULTS}/eval/{{arch}}/photos/{{photoset}}/overlays"),
            patterns=["{photo}.png"],
            caption="../workflow/report/photos_overlay.rst",
            category="Photos",
            subcategory="{photoset}",
            labels={"model": "{arch}", "figure": "{photo}"},
        ),
    log:
        f"{RESULTS}/eval/{{arch}}/photos/{{photoset}}/evaluate_photos.log",
    conda:
        "../envs/train.yaml"
    threads: photo_threads
    params:
        stage=photo_params,
        out_dir=lambda wildcards, output: os.path.dirname(output.metrics),
    shell:
        "psdfactory --log {log:q} evaluate-photos --params {params.stage:q} --model {input.model:q}"
        " --out-dir {params.out_dir:q} --threads {threads}"
