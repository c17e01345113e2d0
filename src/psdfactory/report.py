"""The final report: one self-contained HTML file and a Markdown twin."""

from __future__ import annotations

import base64
import datetime as dt
import html
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import PsdError, __version__
from .config import evaluation_datasets, rerender_splits
from .io import atomic_path, copy_file, pyplot, read_json, save_figure
from .manifest import read_shards
from .psd import NAMES


@dataclass(frozen=True)
class ReportInputs:
    """Every file the report reads, as the workflow names them: nothing is found by walking folders."""

    metrics: dict[str, Path]  # architecture → eval/<arch>/metrics.json
    scatters: dict[str, Path]  # architecture → eval/<arch>/scatter.png
    histories: dict[str, Path]  # architecture → models/<arch>/history.csv
    bench: dict[str, Path]  # architecture → bench/<arch>.json
    manifests: list[Path]  # the scene shards of every dataset
    contact_sheets: dict[str, Path] = field(default_factory=dict)  # dataset → <dataset>/contact_sheet.png
    compare: tuple[Path, Path] | None = None  # the backend comparison: (compare.json, compare.png)
    ceilings: dict[str, Path] = field(default_factory=dict)  # dataset → <dataset>/ceiling.json

    @classmethod
    def from_lists(cls, config: dict, metrics: list, scatters: list, histories: list, bench: list, manifests: list,
                   contact_sheets: list | None = None, compare: list | None = None,
                   ceilings: list | None = None) -> ReportInputs:
        """Per-architecture lists in the order of ``train.architectures`` (a list keeps its
        order through the rule's JSON); a dataset's files (``<results>/<dataset>/contact_sheet.png``,
        ``.../ceiling.json``) keyed by their dataset's folder, not by position: the config reaches
        the report as JSON with sorted keys, so ``datasets`` comes in another order than the
        rule's ``expand()``."""
        archs, datasets = list(config["train"]["architectures"]), list(config["datasets"])

        def keyed(what: str, files: list, keys: list[str]) -> dict[str, Path]:
            if len(files) != len(keys):
                raise PsdError(f"{what}: {len(files)} files for {len(keys)} entries ({', '.join(keys)})")
            return dict(zip(keys, map(Path, files), strict=True))

        def by_dataset(what: str, files: list) -> dict[str, Path]:
            out = {Path(f).parent.name: Path(f) for f in files}
            if len(out) != len(files) or set(out) != set(datasets):
                raise PsdError(f"{what}: expected one file in the folder of each dataset ({', '.join(datasets)}), "
                               f"got {', '.join(map(str, files))}")
            return out

        return cls(keyed("metrics", metrics, archs), keyed("scatters", scatters, archs),
                   keyed("histories", histories, archs), keyed("bench", bench, archs), [Path(m) for m in manifests],
                   by_dataset("contact sheets", contact_sheets) if contact_sheets else {},
                   (Path(compare[0]), Path(compare[1])) if compare else None,
                   by_dataset("ceilings", ceilings) if ceilings else {})


def dataset_tables(manifests: list[Path], datasets: list[str]) -> dict:
    """Each dataset's scene table, from the given shards."""
    scenes = read_shards(manifests)
    names = np.asarray(scenes.column("dataset").to_pylist(), dtype=object)
    out = {}
    for ds in datasets:
        out[ds] = scenes.filter(names == ds)
        if out[ds].num_rows == 0:
            raise PsdError(f"the manifest shards given hold no scene of dataset {ds!r}")
    return out


def label_kind(table) -> str:
    """What a dataset's labels d*_mm are of, e.g. 'sieve size, number-weighted'."""
    kinds = sorted(set(zip(table.column("size_definition").to_pylist(), table.column("weighting").to_pylist(),
                           strict=True)))
    return "; ".join(f"{d} size, {w}-weighted" for d, w in kinds)


def label_histograms(tables: dict, out: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(2, 3, figsize=(11, 5.5))
    for ds, t in tables.items():
        for row, suffix, kind in ((0, "_mm", "the targets"), (1, "_v_mm", "volume-weighted")):
            for j, n in enumerate(NAMES):
                ax = axes[row, j]
                ax.hist(np.asarray(t.column(f"{n}{suffix}")), bins=20, alpha=0.6, label=ds)
                ax.set_title(f"{n} ({kind})", fontsize=9)
                ax.set_xlabel("mm")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out, dpi=90)


def _fmt(v, nd=4) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "–"
    return f"{v:.{nd}f}"


def _r2_of_ceiling(r2: float, ceiling: float | None) -> str:
    """R² and, where the ceiling is known and positive, the fraction of it reached."""
    if ceiling is None or not np.isfinite(ceiling) or ceiling <= 0:
        return _fmt(r2, 3)
    return f"{_fmt(r2, 3)} ({100 * r2 / ceiling:.0f} %)"


def accuracy_table(metrics: dict[str, dict], dataset: str, ceiling: dict | None = None,
                   rerenders: dict[str, str] | None = None) -> tuple[list[str], list[list[str]]]:
    """Per-target R² first, each with the fraction of the dataset's visible-particle ceiling it
    reaches; then R² on each re-render of the dataset's test scenes (another renderer: the
    stand-in for real photos); then MAE, relative error, the pooled overall figures and order
    violations. The ceilings themselves lead the table."""
    vis = (ceiling or {}).get("visible") or {}
    rerenders = rerenders or {}
    head = ["model"] + [f"R² {n} (of ceiling)" for n in NAMES]
    for label in rerenders.values():
        head += [f"R² {n} on {label} renders" for n in NAMES]
    head += [f"MAE {n}" for n in NAMES] + [f"rel. err. {n}" for n in NAMES]
    head += ["R² overall", "MSE overall", "MAE overall", "order violations"]
    width = len(head)
    rows = []
    for kind, what in (("visible", "ceiling: true sizes of the visible particles"),
                       ("footprints", "ceiling: perfect segmentation (footprints of the true masks)"),
                       ("sampling", "ceiling: the generator's μ and σ")):
        c = (ceiling or {}).get(kind)
        if c:
            cells = [_fmt(c[f"{n}_mm"], 3) if kind == "visible" else _r2_of_ceiling(c[f"{n}_mm"], vis.get(f"{n}_mm"))
                     for n in NAMES]
            fitted = (ceiling or {}).get("fitted_on")
            if fitted:  # a re-render's: read-outs fitted on its source's other scenes
                what += f" (fitted on {fitted['n_scenes']} scenes of {fitted['dataset']})"
            rows.append([what] + cells + ["–"] * (width - 4))
    for arch, m in metrics.items():
        d = m["datasets"].get(dataset)
        if d is None:
            continue
        r = [arch] + [_r2_of_ceiling(d[n]["r2"], vis.get(f"{n}_mm")) for n in NAMES]
        for ds in rerenders:
            x = m["datasets"].get(ds)
            r += [_r2_of_ceiling(x[n]["r2"], vis.get(f"{n}_mm")) if x else "–" for n in NAMES]
        r += [_fmt(d[n]["mae"], 3) for n in NAMES] + [f"{100 * d[n]['rel_err']:.1f} %" for n in NAMES]
        r += [_fmt(d["overall"]["r2"]), _fmt(d["overall"]["mse"]), _fmt(d["overall"]["mae"]),
              f"{100 * d['order_violations']:.1f} %"]
        rows.append(r)
    return head, rows


def rerenders_of(config: dict, dataset: str) -> dict[str, str]:
    """The re-render datasets of `dataset`'s scenes → a label naming their renderer."""
    out = {}
    for name, ds in config["datasets"].items():
        if ds.get("rerender_of", {}).get("dataset") == dataset and "test" in rerender_splits(ds):
            backend = (ds.get("render") or config["render"])["backend"]
            out[name] = f"{'Cycles' if backend == 'cycles' else 'TinyRenderer'} ({name})"
    return out


ACCURACY_NOTE = ('Labels are the d10/d50/d90 of the size definition and weighting the dataset table names '
                 '(labels.size_definition, labels.weighting; by default the sieve size — the side of the smallest '
                 "square hole a particle passes — number-weighted as the paper's labels), evaluated on each "
                 "dataset's test split. Per-target R² leads: each is shown with the fraction of the dataset's "
                 'visible-particle ceiling it reaches — the R² of a cross-validated linear read-out of the labels '
                 'from the TRUE sizes of the particles visible in the image, i.e. what a perfect measurement of what'
                 " the camera sees would give. The footprint ceiling is the instance estimator's own read-out fitted"
                 ' to the footprints of the TRUE masks: a perfect segmentation, measured as the estimator measures '
                 "(a partly hidden grain shows less than its sieve size). Where the generator's μ and σ vary, the "
                 "sampling ceiling (labels read from μ, σ alone) shows how much a scene's particles scatter around "
                 "their distribution. A re-render's ceilings are fitted on its source dataset's other scenes (its "
                 'few scenes would make a cross-validation unstable) and scored on its own, as a model is. A '
                 're-render column is the same test scenes rendered by another renderer: how far the model measures '
                 "particles rather than one renderer's look. 'Overall' pools the three targets as the paper's table "
                 '2 does; it reads high for any model that knows d10 < d50 < d90.')


def instance_table(metrics: dict[str, dict], datasets: list[str]) -> tuple[list[str], list[list[str]]]:
    """The instance estimator's own figures per dataset: calibrated vs raw R², segmentation
    precision / recall / F1 at IoU 0.5, and the size error of matched particles; empty without
    an instance model."""
    from .learn.particles import SIEVE_METHODS

    head = (["model", "dataset"] + [f"R² {n} calibrated" for n in NAMES] + [f"R² {n} raw" for n in NAMES]
            + ["precision", "recall", "F1", "size error median", "size error p90"]
            + [f"fully visible: {m.replace('_', ' ')} median / p90" for m in SIEVE_METHODS])
    rows = []

    def pct(e: dict | None) -> str:
        return "–" if not e or not e.get("n") else f"{100 * e['median']:.1f} % / {100 * e['p90']:.1f} %"

    for arch, m in metrics.items():
        for ds in datasets:
            d = m["datasets"].get(ds)
            if not d or "segmentation" not in d:
                continue
            seg, se = d["segmentation"], d["size_error"]
            matched = se["matched"][se["method"]]
            vis = se.get("matched_fully_visible", {})
            rows.append([arch, ds] + [_fmt(d[n]["r2"], 3) for n in NAMES] + [_fmt(d["raw"][n]["r2"], 3) for n in NAMES]
                        + [_fmt(seg["precision"], 3), _fmt(seg["recall"], 3), _fmt(seg["f1"], 3),
                           "–" if not matched["n"] else f"{100 * matched['median']:.1f} %",
                           "–" if not matched["n"] else f"{100 * matched['p90']:.1f} %",
                           *(pct(vis.get(meth)) for meth in SIEVE_METHODS)])
    return head, rows


INSTANCE_NOTE = ("The instance estimator segments every particle (a ResNet-18-trunk encoder-decoder predicting "
                 "foreground, boundary, distance and size maps, then a watershed), measures each one, and reads "
                 "d10/d50/d90 off the measured particles: 'raw' = the number-weighted percentiles of the particles "
                 "not touching the image edge; 'calibrated' = a ridge read-out from the instance statistics to the "
                 "labels fitted on the training and validation scenes (the camera cannot see the hidden fines) — the"
                 " figure the accuracy table shows. Precision / recall / F1: predicted vs true instances matched "
                 "one-to-one at IoU ≥ 0.5. Size error: |estimated − true sieve size| / true size of matched "
                 "particles not touching the edge, with the model's sieve method; 'fully visible' also excludes any "
                 "particle bordering a higher one (it may be partly hidden), per method: min Feret diameter and "
                 "ellipse minor axis of the footprint, and the size map (the network's estimate of the whole "
                 "particle, median over the instance).")


def fast_path_rule(bench: dict[str, dict]) -> str:
    budget = next((r["max_r2_change"] for b in bench.values() for r in b["results"]), None)
    cpus = sorted({b["cpu"]["summary"] for b in bench.values() if "cpu" in b})
    skipped = sorted({f"{k} ({why})" for b in bench.values() for r in b["results"] for k, why in r["skipped"].items()})
    text = ("Every inference path worth trying on this machine is timed side by side in one run (median of repeated "
            "runs) and checked on the test split; the fast path (★) is the fastest whose overall R² stays within "
            f"±{budget} of fp32 eager's, chosen by measurement. CPU: {'; '.join(cpus) or 'not recorded'}.")
    if skipped:
        text += " Not tried here: " + "; ".join(skipped) + "."
    return text


def speed_table(bench: dict[str, dict]) -> tuple[list[str], list[list[str]]]:
    """One row per model, device and measured path."""
    head = ["CNN model", "device", "input px", "path", "batch 1 (img/s)", "batched (img/s)", "ms/image (batched)",
            "speed-up vs fp32 (batched)", "R² change vs fp32", "Parameters (M)", "GFLOPs"]
    rows = []
    for arch, b in bench.items():
        for r in b["results"]:
            base = r["paths"]["fp32"]["batched"]["images_per_s"]
            for key, p in r["paths"].items():
                if key == "fast":
                    continue
                change = p.get("r2_change")
                name = p["name"] + (" ★" if key == r["fast_key"] else "")
                rows.append([arch, r["device"], str(r["input_size"]), name,
                             _fmt(p["batch1"]["images_per_s"], 1), _fmt(p["batched"]["images_per_s"], 1),
                             _fmt(p["batched"]["ms_per_image"], 2), f"{p['batched']['images_per_s'] / base:.2f}×",
                             "–" if change is None else f"{change:+.4f}", _fmt(r["params_m"], 1), _fmt(r["gflops"], 2)])
    return head, rows


def _md_table(head, rows) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _html_table(head, rows) -> str:
    h = "".join(f"<th>{html.escape(c)}</th>" for c in head)
    b = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{h}</tr></thead><tbody>{b}</tbody></table>"


def _img_tag(path: Path, alt: str) -> str:
    data = base64.b64encode(Path(path).read_bytes()).decode()
    return (f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(alt)}</figcaption></figure>")


def build_report(config: dict, inputs: ReportInputs, out_html: Path, out_md: Path) -> None:
    import yaml

    datasets = list(config["datasets"])
    archs = list(config["train"]["architectures"])
    fig_dir = out_md.parent / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    metrics = {a: read_json(inputs.metrics[a]) for a in archs}
    bench = {a: read_json(inputs.bench[a]) for a in archs}
    for a in archs:
        for what, files, got in (("metrics", inputs.metrics, metrics[a]), ("bench", inputs.bench, bench[a])):
            if got.get("arch") != a:
                raise PsdError(f"{files[a]} holds the {what} of {got.get('arch')!r}, not of {a!r}")
    histories = inputs.histories
    tables = dataset_tables(inputs.manifests, datasets)

    figures: list[tuple[Path, str]] = []
    hist_png = fig_dir / "label_histograms.png"
    label_histograms(tables, hist_png)
    kinds = "; ".join(sorted({label_kind(t) for t in tables.values()}))
    figures.append((hist_png, f"Label distributions per dataset (the targets: {kinds}; below, volume-weighted)"))
    for ds, sheet in inputs.contact_sheets.items():
        dst = fig_dir / f"contact_sheet_{ds}.png"
        copy_file(sheet, dst)
        figures.append((dst, f"Contact sheet: {ds}"))
    compare_head, compare_rows = [], []
    if inputs.compare is not None:
        summary = read_json(inputs.compare[0])
        dst = fig_dir / "compare_backends.png"
        copy_file(inputs.compare[1], dst)
        figures.append((dst, "The same scenes rendered by TinyRenderer and Blender Cycles"))
        compare_head = ["scene", "particles", "tiny (s)", "cycles (s)", "masks agree", "agree off edges"]
        compare_rows = [[r["scene_id"], str(r["n_particles"]), f"{r['seconds_tiny']:.1f}", f"{r['seconds_cycles']:.1f}",
                         f"{100 * r['mask_agreement']:.1f} %", f"{100 * r['mask_agreement_off_edges']:.2f} %"]
                        for r in summary["scenes"]]
    from .learn.evaluate import plot_history

    plot_figs = []
    for a in archs:
        curve = fig_dir / f"loss_{a}.png"
        plot_history(histories[a], a, curve)
        scatter = fig_dir / f"scatter_{a}.png"
        copy_file(inputs.scatters[a], scatter)
        plot_figs += [(scatter, f"{a}: predicted vs true"), (curve, f"{a}: training and validation loss")]

    # dataset summary
    count_head = ["dataset", "scenes", "train", "val", "test", "particles / scene", "mm / px", "shape", "labels of"]
    count_rows = []
    for ds, t in tables.items():
        splits = t.column("split").to_pylist()
        n = np.asarray(t.column("n_particles"))
        count_rows.append([ds, str(t.num_rows), *(str(splits.count(s)) for s in ("train", "val", "test")),
                           f"{n.min()}–{n.max()}", f"{np.median(np.asarray(t.column('mm_per_px'))):.3f}",
                           ", ".join(sorted(set(t.column("shape_type").to_pylist()))), label_kind(t)])
    weights = [[a, metrics[a]["weights"]] for a in archs]
    fallback = [a for a in archs if "unavailable" in metrics[a]["weights"]]
    warning = (f"ImageNet weights were not available for {', '.join(fallback)}: trained from scratch "
               "(train.pretrained: auto). Expect lower accuracy than with pretrained weights.") if fallback else ""
    speed_head, speed_rows = speed_table(bench)
    cfg_yaml = yaml.safe_dump(config, sort_keys=False)
    when = dt.datetime.now().strftime("%Y-%m-%d %H:%M")

    md = ["# psdfactory report", "", f"Generated {when} by psdfactory {__version__}.", ""]
    if warning:
        md += [f"> **Warning:** {warning}", ""]
    md += ["## Datasets", "", _md_table(count_head, count_rows), ""]
    if compare_rows:
        md += ["Render backends compared on the same settled poses "
               f"({summary['resolution']} px, Cycles at {summary['cycles'].get('samples', '?')} samples):", "",
               _md_table(compare_head, compare_rows), ""]
    md += [f"![{c}](figures/{p.name})" for p, c in figures] + [""]
    ceilings = {ds: read_json(f) for ds, f in inputs.ceilings.items()}
    tested = evaluation_datasets(config)  # not the re-renders that are training images only
    acc = {ds: accuracy_table(metrics, ds, ceilings.get(ds), rerenders_of(config, ds)) for ds in tested}
    md += ["## Accuracy", "", ACCURACY_NOTE, ""]
    for ds in tested:
        md += [f"### {ds}", "", _md_table(*acc[ds]), ""]
    inst_head, inst_rows = instance_table(metrics, datasets)
    if inst_rows:
        md += ["## Instance estimator", "", INSTANCE_NOTE, "", _md_table(inst_head, inst_rows), ""]
    md += ["## Inference speed", "", fast_path_rule(bench), "", _md_table(speed_head, speed_rows), ""]
    md += [f"![{c}](figures/{p.name})" for p, c in plot_figs] + [""]
    md += ["## Weights used", "", _md_table(["CNN model", "weights"], weights), ""]
    md += ["## Configuration", "", "```yaml", cfg_yaml.rstrip(), "```", ""]
    with atomic_path(out_md) as tmp:
        tmp.write_text("\n".join(md))

    style = ("body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}"
             "table{border-collapse:collapse;margin:1em 0;font-size:13px}td,th{border:1px solid #ccc;padding:3px 6px;"
             "text-align:right}th{background:#f3f3f3}td:first-child{text-align:left}img{max-width:100%}"
             "figure{display:inline-block;margin:0.5em;vertical-align:top;max-width:48%}"
             ".warn{background:#fff3cd;border:1px solid #e0c36a;padding:0.6em 1em}pre{background:#f7f7f7;padding:1em;"
             "overflow:auto;font-size:12px}")
    h = [f"<!doctype html><html><head><meta charset='utf-8'><title>psdfactory report</title><style>{style}</style>"
         "</head><body>", "<h1>psdfactory report</h1>", f"<p>Generated {when} by psdfactory {__version__}.</p>"]
    if warning:
        h.append(f"<p class='warn'><b>Warning:</b> {html.escape(warning)}</p>")
    h += ["<h2>Datasets</h2>", _html_table(count_head, count_rows)]
    if compare_rows:
        h += [f"<p>Render backends compared on the same settled poses ({summary['resolution']} px, Cycles at "
              f"{summary['cycles'].get('samples', '?')} samples):</p>", _html_table(compare_head, compare_rows)]
    h += [_img_tag(p, c) for p, c in figures]
    h += ["<h2>Accuracy</h2>", f"<p>{html.escape(ACCURACY_NOTE)}</p>"]
    for ds in tested:
        h += [f"<h3>{html.escape(ds)}</h3>", _html_table(*acc[ds])]
    if inst_rows:
        h += ["<h2>Instance estimator</h2>", f"<p>{html.escape(INSTANCE_NOTE)}</p>", _html_table(inst_head, inst_rows)]
    h += ["<h2>Inference speed</h2>", f"<p>{html.escape(fast_path_rule(bench))}</p>",
          _html_table(speed_head, speed_rows)]
    h += [_img_tag(p, c) for p, c in plot_figs]
    h += ["<h2>Weights used</h2>", _html_table(["CNN model", "weights"], weights)]
    h += ["<h2>Configuration</h2>", f"<pre>{html.escape(cfg_yaml)}</pre>", "</body></html>"]
    with atomic_path(out_html) as tmp:
        tmp.write_text("\n".join(h))
