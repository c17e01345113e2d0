"""The final report: one self-contained HTML file and a Markdown twin."""

from __future__ import annotations

import base64
import datetime as dt
import html
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import PsdError, __version__
from .config import (
    dataset_render,
    evaluation_datasets,
    main_training_dataset,
    rerender_splits,
    train_params,
    trained_datasets,
    training_recipe,
)
from .io import atomic_path, copy_file, pyplot, read_json, save_figure
from .manifest import read_shards
from .paper import TABLE2, TABLE2_TEST, TABLE3, TABLE3_CPU, TABLE3_GPU
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
    photos: dict[str, dict[str, Path]] = field(default_factory=dict)  # arch → photo set → its metrics.json
    spread: Path | None = None  # bench/seed_spread.py's spread.json (SPREAD_JSON under the results), where measured

    @classmethod
    def from_lists(cls, config: dict, metrics: list, scatters: list, histories: list, bench: list, manifests: list,
                   contact_sheets: list | None = None, compare: list | None = None,
                   ceilings: list | None = None, photos: list | None = None,
                   spread: str | Path | None = None) -> ReportInputs:
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
                   by_dataset("ceilings", ceilings) if ceilings else {},
                   photo_inputs(archs, list(config.get("photos") or {}), photos or []),
                   Path(spread) if spread else None)


def photo_inputs(archs: list[str], sets: list[str], files: list) -> dict[str, dict[str, Path]]:
    """eval/<arch>/photos/<set>/metrics.json files keyed by their folders: one for every model and
    photo set of the config, none else."""
    out: dict[str, dict[str, Path]] = {}
    for f in map(Path, files):
        arch, name = f.parents[2].name, f.parent.name
        if f.parents[1].name != "photos" or arch not in archs or name not in sets or name in out.get(arch, {}):
            raise PsdError(f"photos: {f} is not eval/<arch>/photos/<set>/metrics.json of one of the models "
                           f"({', '.join(archs)}) and photo sets ({', '.join(sets) or 'none'}), once each")
        out.setdefault(arch, {})[name] = f
    if files and sum(map(len, out.values())) != len(archs) * len(sets):
        raise PsdError(f"photos: {len(files)} metrics files for {len(archs)} models x {len(sets)} photo sets")
    return out


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


# The label histograms are shown at the report's full width (at most ~970 px): a figure 9.6 in wide
# at 100 dpi is 960 px, so its smallest font (HIST_MIN_PT) shows at ~HIST_MIN_PT * 100 / 72 px.
HIST_FIGSIZE = (9.6, 5.4)
HIST_DPI = 100
HIST_MIN_PT = 10


def label_histograms(tables: dict, out: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(2, 3, figsize=HIST_FIGSIZE)
    for ds, t in tables.items():
        for row, suffix, kind in ((0, "_mm", "the targets"), (1, "_v_mm", "volume-weighted")):
            for j, n in enumerate(NAMES):
                ax = axes[row, j]
                ax.hist(np.asarray(t.column(f"{n}{suffix}")), bins=20, alpha=0.6, label=ds)
                ax.set_title(f"{n} ({kind})", fontsize=HIST_MIN_PT + 1)
                ax.set_xlabel("mm", fontsize=HIST_MIN_PT)
                ax.set_ylabel("scenes", fontsize=HIST_MIN_PT)
                ax.tick_params(labelsize=HIST_MIN_PT)
    # one legend under the panels, in as many columns as the names allow (long names: one a row)
    longest = max((len(ds) for ds in tables), default=1)
    ncol = max(1, min(len(tables), 90 // (longest + 6)))
    rows = -(-len(tables) // ncol)
    fig.legend(*axes[0, 0].get_legend_handles_labels(), loc="lower center", ncol=ncol, fontsize=HIST_MIN_PT,
               frameon=False)
    fig.tight_layout(rect=(0, min(0.5, 0.01 + 0.045 * rows), 1, 1))
    save_figure(fig, out, dpi=HIST_DPI)


MISSING = "—"  # a figure that does not exist (or, beside an R², a fraction that would mislead)


def _fmt(v, nd=4) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return MISSING
    return f"{v:.{nd}f}"


def _finite(v) -> bool:
    return isinstance(v, int | float) and bool(np.isfinite(v))


def _r2_of_ceiling(r2: float, ceiling: float | None) -> str:
    """R² and, where the ceiling is known, the fraction of it reached — only where both are
    positive: a fraction of a negative R² (or of a negative ceiling) reads as nonsense (e.g.
    −4.6 as "−557 %"), so it shows "—"."""
    if ceiling is None or not _finite(ceiling):
        return _fmt(r2, 3)
    if not _finite(r2) or r2 <= 0 or ceiling <= 0:
        return f"{_fmt(r2, 3)} ({MISSING})"
    return f"{_fmt(r2, 3)} ({100 * r2 / ceiling:.0f} %)"


CEILING_ROWS = (("visible", "ceiling: true sizes of the visible particles"),
                ("footprints", "ceiling: perfect segmentation (footprints of the true masks)"),
                ("sampling", "ceiling: the generator's μ and σ"))


def _ceiling_rows(ceiling: dict | None, width: int) -> list[list[str]]:
    """The rows of a dataset's ceilings: the visible one's R², the others' as a fraction of it."""
    vis = (ceiling or {}).get("visible") or {}
    rows = []
    for kind, what in CEILING_ROWS:
        c = (ceiling or {}).get(kind)
        if c:
            cells = [_fmt(c[f"{n}_mm"], 3) if kind == "visible" else _r2_of_ceiling(c[f"{n}_mm"], vis.get(f"{n}_mm"))
                     for n in NAMES]
            fitted = (ceiling or {}).get("fitted_on")
            if fitted:  # a re-render's: read-outs fitted on its source's other scenes
                what += f" (fitted on {fitted['n_scenes']} scenes of {fitted['dataset']})"
            rows.append([what] + cells + [MISSING] * (width - 4))
    return rows


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
    head += [f"MAE {n} (mm)" for n in NAMES] + [f"rel. err. {n}" for n in NAMES]
    head += ["R² overall", "MSE overall (mm²)", "MAE overall (mm)", "order violations"]
    rows = _ceiling_rows(ceiling, len(head))
    for arch, m in metrics.items():
        d = m["datasets"].get(dataset)
        if d is None:
            continue
        r = [arch] + [_r2_of_ceiling(d[n]["r2"], vis.get(f"{n}_mm")) for n in NAMES]
        for ds in rerenders:
            x = m["datasets"].get(ds)
            r += [_r2_of_ceiling(x[n]["r2"], vis.get(f"{n}_mm")) if x else MISSING for n in NAMES]
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


RENDERER_NAMES = {"tiny": "TinyRenderer", "cycles": "Cycles"}
EXTERNAL = "outside images (e.g. photos)"


def renderer_of(config: dict, dataset: str) -> str:
    """What made a dataset's images: its renderer, or, for a dataset the config does not define
    (evaluated on images brought from elsewhere, e.g. photos), EXTERNAL."""
    if dataset not in config["datasets"]:
        return EXTERNAL
    backend = dataset_render(config, dataset)["backend"]
    return RENDERER_NAMES.get(backend, backend)


def evaluated_datasets(config: dict, metrics: dict[str, dict]) -> list[str]:
    """Every dataset any model was evaluated on, the training datasets first, then the others of
    the training renderers, then other renderers, then datasets from outside the config (the
    config reaches the report as JSON with sorted keys: its order says nothing)."""
    train = trained_datasets(config)
    seen = [ds for m in metrics.values() for ds in m["datasets"]]
    trained_with = {renderer_of(config, d) for d in train if d in config["datasets"]}

    def rank(ds: str) -> tuple:
        if ds in train:
            return 0, train.index(ds), ds
        if ds not in config["datasets"]:
            return 3, 0, ds
        return (1 if renderer_of(config, ds) in trained_with else 2), 0, ds

    return sorted(dict.fromkeys(seen), key=rank)


def mean_true(tables: dict, dataset: str, metrics_of: dict) -> dict[str, float] | None:
    """The mean true d10/d50/d90 (mm) of the scenes a model was scored on (eval_rows: the test
    split, or all scenes without one), from the manifests; None where they are not in the shards
    given or their count differs from the metrics' (then no relative error is shown)."""
    t = tables.get(dataset)
    if t is None:
        return None
    split = np.asarray(t.column("split").to_pylist(), dtype=object)
    sel = split == "test" if metrics_of.get("split", "test") == "test" else np.ones(len(split), bool)
    if int(sel.sum()) != metrics_of.get("n") or not sel.any():
        return None
    return {n: float(np.mean(np.asarray(t.column(f"{n}_mm"))[sel])) for n in NAMES}


SUMMARY_TARGETS = ("d50", "d90")
R2_MARGIN = 0.05  # a model within this mean R² of the best counts as "as good" for the fast pick


@dataclass(frozen=True)
class SummaryColumn:
    dataset: str
    renderer: str
    split: str  # e.g. "test split, 24 scenes"
    mean_true: dict[str, float] | None  # per target, mm (None: no relative error)


@dataclass(frozen=True)
class Summary:
    """The report's answer to "which model, how good, how fast"."""

    columns: list[SummaryColumn]
    r2: dict[str, dict[str, list[str]]]  # model → dataset → [R² d50, R² d90] formatted
    err: dict[str, dict[str, list[str]]]  # model → dataset → [error d50, error d90] formatted
    devices: list[str]
    speed: dict[str, dict[str, float]]  # model → device → fast path, batched images/s
    batch: dict[str, int]  # model → its batched runs' batch size
    yardstick: str  # what the recommendation ranks on, in words
    use: dict[str, str]  # model → "use for …" line
    note: str
    photo_sets: list[PhotoColumn] = field(default_factory=list)  # the config's photo sets evaluated
    photo_cells: dict[str, dict[str, list[str]]] = field(default_factory=dict)  # model → set → [F1, PSD error]


@dataclass(frozen=True)
class PhotoColumn:
    name: str
    about: str  # e.g. "2 photos vs reference (ellipse-minor)"


def photo_summary(photos: dict[str, dict[str, dict]]) -> tuple[list[PhotoColumn], dict[str, dict[str, list[str]]]]:
    """The summary card's photo column groups: per photo set, per model, the pooled F1 of the grains
    found and the mean |relative error| of d50 / d90 against the reference (a model that finds no
    grains has no F1, and its error is of its own reading, in its own size definition)."""
    sets = list(dict.fromkeys(s for per in photos.values() for s in per))
    columns = []
    for s in sets:
        first = next(per[s] for per in photos.values() if s in per)
        n = len(first["photos"])
        columns.append(PhotoColumn(s, f"{n} photo{'s' * (n != 1)} vs reference ({first['size_definition']})"))
    cells = {}
    for arch, per in photos.items():
        cells[arch] = {}
        for s, m in per.items():
            det = m["pooled"].get("detection")
            err = m["pooled"]["psd_abs_rel_err"]
            cells[arch][s] = [_fmt(det["f1"], 2) if det else MISSING,
                              " / ".join(_pct(err.get(n)) for n in SUMMARY_TARGETS)]
    return columns, cells


def _mean_score(d: dict | None) -> float | None:
    """The mean of the d50 and d90 R² of one model on one dataset."""
    if not d:
        return None
    vals = [d.get(n, {}).get("r2") for n in SUMMARY_TARGETS]
    return float(np.mean(vals)) if all(_finite(v) for v in vals) else None


def _pct(v: float | None) -> str:
    return MISSING if v is None or not np.isfinite(v) else (f"{100 * v:.0f} %" if v >= 0.1 else f"{100 * v:.1f} %")


def _ips(v: float | None) -> str:
    return MISSING if v is None else (f"{v:.0f}" if v >= 10 else f"{v:.1f}")


def summarize(config: dict, metrics: dict[str, dict], bench: dict[str, dict], tables: dict,
              photos: dict[str, dict[str, dict]] | None = None) -> Summary:
    """Per model, the d50/d90 R² and relative error (MAE ÷ mean true size) on every evaluated
    dataset, the images/s of its fast path, and a recommendation computed from them: "measure
    with" the best mean d50/d90 R² on the yardstick (photos where evaluated; else the renderers no
    model was trained on; else every dataset), "when speed matters" the fastest within R2_MARGIN
    of it, and for the rest why not. `photos` (model → photo set → its photo metrics) adds a
    column group per photo set (`photo_summary`): shown, never ranked on — the config's photo sets
    are for measuring, and nothing is chosen by its score on them."""
    archs = list(metrics)
    columns = []
    for ds in evaluated_datasets(config, metrics):
        first = next(m["datasets"][ds] for m in metrics.values() if ds in m["datasets"])
        split = (f"test split, {first.get('n', '?')} scenes" if first.get("split", "test") == "test"
                 else f"all {first.get('n', '?')} scenes")
        columns.append(SummaryColumn(ds, renderer_of(config, ds), split, mean_true(tables, ds, first)))
    r2, err = {}, {}
    for a in archs:
        r2[a], err[a] = {}, {}
        for c in columns:
            d = metrics[a]["datasets"].get(c.dataset)
            r2[a][c.dataset] = [_fmt(d[n]["r2"], 2) if d else MISSING for n in SUMMARY_TARGETS]
            err[a][c.dataset] = [_pct(d[n]["mae"] / c.mean_true[n]) if d and c.mean_true and c.mean_true[n] > 0
                                 else MISSING for n in SUMMARY_TARGETS]
    devices = list(dict.fromkeys(r["device"] for b in bench.values() for r in b["results"]))
    speed = {a: {r["device"]: r["paths"]["fast"]["batched"]["images_per_s"] for r in bench[a]["results"]}
             for a in archs}
    batch = {a: next((r["paths"]["fast"]["batched"].get("batch") for r in bench[a]["results"]), None) for a in archs}
    # ranked on the last device every model was timed on (benchmark's order: the CPU, then the GPU)
    common = [d for d in devices if all(d in speed[a] for a in archs)]
    device = common[-1] if common else None

    # the yardstick: the images least like the training ones
    train = [d for d in trained_datasets(config) if d in config["datasets"]]  # by any model
    trained_with = {renderer_of(config, d) for d in train}
    external = [c for c in columns if c.renderer == EXTERNAL]
    unseen = [c for c in columns if c.renderer not in trained_with and c.renderer != EXTERNAL]
    if external:
        yard = external
        yard_short = "the outside images (" + " and ".join(c.dataset for c in yard) + ")"
        yard_text = yard_short
    elif unseen:
        yard = unseen
        yard_short = "the " + " and ".join(f"{c.renderer} renders ({c.dataset})" for c in yard)
        yard_text = yard_short + (", a renderer no model was trained on" if trained_with else "")
    else:
        yard = columns
        yard_short = yard_text = "every evaluated dataset"
    score = {}
    for a in archs:
        vals = [_mean_score(metrics[a]["datasets"].get(c.dataset)) for c in yard]
        score[a] = float(np.mean(vals)) if vals and all(v is not None for v in vals) else None
    fast = {a: speed[a].get(device) if device else None for a in archs}
    scored = [a for a in archs if score[a] is not None]
    use = {}
    best = max(scored, key=lambda a: score[a]) if scored else None
    near = [a for a in scored if score[a] >= score[best] - R2_MARGIN and fast[a] is not None] if best else []
    quick = max(near, key=lambda a: fast[a]) if near else None
    on = f" on {device}" if device else ""
    if best is not None:
        use[best] = (f"use to measure: the best mean d50/d90 R² on {yard_text}: {score[best]:.2f}"
                     + (f", and the fastest of the models within {R2_MARGIN} of it ({_ips(fast[best])} img/s{on})"
                        if quick == best and len(near) > 1 else "")
                     + ("" if score[best] > 0 else "; but below 0: no model here measures better than guessing "
                        "the mean size"))
    if quick is not None and quick != best:
        ratio = f", {fast[quick] / fast[best]:.1f}× the speed of {best}" if fast[best] else ""
        use[quick] = (f"use when speed matters: {_ips(fast[quick])} img/s{on}{ratio}, mean d50/d90 R² "
                      f"{score[quick]:.2f} on {yard_short}, within {R2_MARGIN} of the best")
    for a in archs:
        if a in use:
            continue
        if score[a] is None:
            use[a] = f"no recommendation: no d50/d90 R² on {yard_short}"
        elif score[a] <= 0:
            use[a] = (f"do not use: mean d50/d90 R² {score[a]:.2f} on {yard_short}, "
                      f"{'worse than' if score[a] < 0 else 'no better than'} always answering the mean size")
        elif quick is not None and fast[a] is not None and fast[a] > fast[quick]:
            use[a] = (f"quick screening only: the fastest ({_ips(fast[a])} img/s{on}), but mean d50/d90 R² "
                      f"{score[a]:.2f} on {yard_short}, {score[best] - score[a]:.2f} below {best}")
        else:
            faster = quick if quick not in (None, best) else best
            use[a] = (f"not recommended: {best} measures better ({score[best]:.2f} vs {score[a]:.2f} mean d50/d90 "
                      f"R² on {yard_short})"
                      + (f" and {faster} is as fast or faster ({_ips(fast[faster])} vs {_ips(fast[a])} img/s{on})"
                         if fast[faster] is not None and fast[a] is not None and fast[faster] >= fast[a] else ""))
    batches = sorted({b for b in batch.values() if b})
    note = ("R²: 1 is perfect, 0 no better than always answering the mean size, below 0 worse. Error: mean absolute "
            "error ÷ the mean true size of the scenes scored (—: their true sizes are not in the manifests given). "
            "Speed: images per second of each model's fast path (Inference speed, below), batched"
            + (f" (batch {', '.join(map(str, batches))})" if batches else "")
            + ", each at its own input size"
            + (f"; ranked on {device}." if device else "."))
    photo_sets, photo_cells = photo_summary(photos or {})
    if photo_sets:
        note += (f" Photos ({', '.join(c.name for c in photo_sets)}): F1 of the grains found against the reference "
                 "masks (IoU ≥ 0.5, grains cut by the border left out) and the mean |relative error| of d50 / d90 "
                 "against the reference's, in its size definition (a model without an F1 finds no grains: the "
                 "error of its own reading, in its own definition); measured, never ranked on.")
    return Summary(columns, r2, err, devices, speed, batch, yard_text, use, note, photo_sets, photo_cells)


def summary_table(s: Summary) -> tuple[list[str], list[list[str]]]:
    """The summary as one flat table (the Markdown twin's; the HTML card groups the columns)."""
    head = ["model"]
    for c in s.columns:
        head += [f"R² d50 / d90 on {c.dataset} ({c.renderer})", f"error d50 / d90 on {c.dataset}"]
    for p in s.photo_sets:
        head += [f"F1 on {p.name} (photos)", f"error d50 / d90 on {p.name}"]
    head += [f"img/s on {d}" for d in s.devices]
    rows = [[a] + [x for c in s.columns for x in (" / ".join(s.r2[a][c.dataset]), " / ".join(s.err[a][c.dataset]))]
            + [x for p in s.photo_sets for x in s.photo_cells.get(a, {}).get(p.name, [MISSING, MISSING])]
            + [_ips(s.speed[a].get(d)) for d in s.devices] for a in s.r2]
    return head, rows


def summary_html(s: Summary, warning: str = "") -> str:
    """The summary card: a table with one column group per evaluated dataset, then a line per model."""
    e = html.escape
    top = "<th rowspan='2'>model</th>" + "".join(
        f"<th colspan='2'>{_wrap(c.dataset)}<br><span class='sub'>{e(c.renderer)}, {e(c.split)}</span></th>"
        for c in s.columns)
    top += "".join(f"<th colspan='2'>{_wrap(p.name)}<br><span class='sub'>photos: {e(p.about)}</span></th>"
                   for p in s.photo_sets)
    top += f"<th colspan='{max(1, len(s.devices))}'>speed</th>"
    sub = "".join("<th>R² d50 / d90</th><th>error d50 / d90</th>" for _ in s.columns)
    sub += "".join("<th>F1</th><th>error d50 / d90</th>" for _ in s.photo_sets)
    sub += "".join(f"<th>img/s<br><span class='sub'>{e(d)}</span></th>" for d in s.devices) or "<th>img/s</th>"
    body = "".join(
        f"<tr><td>{_wrap(a)}</td>"
        + "".join(f"<td>{e(' / '.join(s.r2[a][c.dataset]))}</td><td>{e(' / '.join(s.err[a][c.dataset]))}</td>"
                  for c in s.columns)
        + "".join(f"<td>{e(x)}</td>" for p in s.photo_sets
                  for x in s.photo_cells.get(a, {}).get(p.name, [MISSING, MISSING]))
        + ("".join(f"<td>{e(_ips(s.speed[a].get(d)))}</td>" for d in s.devices) or f"<td>{MISSING}</td>")
        + "</tr>" for a in s.r2)
    uses = "".join(f"<li><b>{_wrap(a)}</b>: {_wrap(u)}</li>" for a, u in s.use.items())
    warn = f"<p class='warn'><b>Warning:</b> {e(warning)}</p>" if warning else ""
    return ("<section id='summary' class='card'><h2>Summary: which model, how good, how fast</h2>"
            f"<div class='tw'><table class='summary'><thead><tr>{top}</tr><tr>{sub}</tr></thead>"
            f"<tbody>{body}</tbody></table></div><ul class='use'>{uses}</ul>"
            f"<p class='note'>{e(s.note)}</p>{warn}</section>")


def compact_accuracy_table(metrics: dict[str, dict], dataset: str,
                           ceiling: dict | None = None) -> tuple[list[str], list[list[str]]]:
    """What fits a narrow page: per-target R² (with the fraction of the visible ceiling) and MAE
    in mm; the ceilings lead. The rest is in accuracy_table."""
    vis = (ceiling or {}).get("visible") or {}
    r2_head = "R² {} (of ceiling)" if vis else "R² {}"
    head = ["model"] + [r2_head.format(n) for n in NAMES] + [f"MAE {n} (mm)" for n in NAMES]
    rows = _ceiling_rows(ceiling, len(head))
    for arch, m in metrics.items():
        d = m["datasets"].get(dataset)
        if d is not None:
            rows.append([arch] + [_r2_of_ceiling(d[n]["r2"], vis.get(f"{n}_mm")) for n in NAMES]
                        + [_fmt(d[n]["mae"], 3) for n in NAMES])
    return head, rows


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
    an instance model. The sieve methods are those the metrics hold (the report needs none of the
    estimator's code)."""
    methods = list(dict.fromkeys(meth for m in metrics.values() for d in m["datasets"].values()
                                 for meth in (d.get("size_error") or {}).get("matched_fully_visible", {})))
    head = (["model", "dataset"] + [f"R² {n} calibrated" for n in NAMES] + [f"R² {n} raw" for n in NAMES]
            + ["precision", "recall", "F1", "size error median", "size error p90"]
            + [f"fully visible: {m.replace('_', ' ')} median / p90" for m in methods])
    rows = []

    def pct(e: dict | None) -> str:
        return MISSING if not e or not e.get("n") else f"{100 * e['median']:.1f} % / {100 * e['p90']:.1f} %"

    for arch, ds, d in _segmented(metrics, datasets):
        vis = d["size_error"].get("matched_fully_visible", {})
        rows.append([arch, ds] + [_fmt(d[n]["r2"], 3) for n in NAMES] + [_fmt(d["raw"][n]["r2"], 3) for n in NAMES]
                    + _segmentation_cells(d) + [pct(vis.get(meth)) for meth in methods])
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


PHOTOS_NOTE = ("Each photo is read at its own mm per pixel and resized to the model's scale, as predict does. "
               "Grains found vs the reference grains: matched one-to-one at IoU ≥ 0.5 at the photo's resolution (the "
               "model's instance mask resized nearest-neighbour to it, the reference masks as they are); reference "
               "grains cut by the image border are left out, and a grain found on the border counts only if it "
               "matches a reference grain (P: precision, R: recall). Size error: median / p90 of |est − ref| / ref of "
               "the matched grains not touching the border, in the reference's size definition and of the model's "
               "sieve-size estimate. d10 / d50 / d90: number-weighted percentiles of the grains found not touching "
               "the border, in the reference's definition, and their error relative to the reference; a model that "
               "finds no grains gives its own reading, in its own definition. The reference is a peer tool's "
               "segmentation, not hand truth; these photos are for measuring only: nothing is fitted or chosen on "
               "them.")


def _signed_pct(v) -> str:
    return MISSING if v is None or not _finite(v) else f"{100 * v:+.0f} %"


def _three(d: dict | None, fmt) -> str:
    return MISSING if not d else " / ".join(fmt(d.get(n)) for n in NAMES)


def _error_pair(e: dict | None) -> str:
    return MISSING if not e or not e.get("n") else f"{100 * e['median']:.1f} % / {100 * e['p90']:.1f} %"


def photo_table(m: dict) -> tuple[list[str], list[list[str]]]:
    """One model on one photo set: a row per photo, then the pooled row (sums, the pooled grains,
    the mean |relative error| of the d-values); where the set restores its references' outlines,
    the same rows again against those. A model that finds no grains: its d-values only."""
    grains = bool(m["finds_grains"])
    psd_head = ["d10 / d50 / d90 (mm)", "reference (mm)", "error d10 / d50 / d90"]
    head = ["photo", *(["grains found / reference", "P", "R", "F1", "size error median / p90",
                        "sieve estimate error median / p90"] if grains else []), *psd_head]

    def mm(v) -> str:
        return _fmt(v, 1) if _finite(v) and v >= 10 else _fmt(v, 2)

    def counts(found, ref) -> str:
        return MISSING if found is None else f"{found} / {MISSING if ref is None else ref}"

    def photo_row(label: str, r: dict, figures: dict) -> list[str]:
        det, se = figures.get("detection") or {}, figures.get("size_error") or {}
        found = [counts(r.get("n_found_off_border"), figures.get("n_reference")),
                 *(_fmt(det.get(k), 3) for k in ("precision", "recall", "f1")),
                 _error_pair(se.get("size_definition")), _error_pair(se.get("sieve"))]
        mark = "⚠ " if r.get("warning") else ""  # the warning is under the table
        return [label, *(found if grains else []), mark + _three(r["psd_mm"], mm),
                _three(figures.get("reference_mm"), mm), _three(figures["psd_rel_err"], _signed_pct)]

    def pooled_row(label: str, p: dict, figures: list[dict]) -> list[str]:
        det, se = p.get("detection") or {}, p.get("size_error") or {}
        n_found = [r.get("n_found_off_border") for r in m["photos"].values()]
        refs = [f.get("n_reference") for f in figures]
        found = [counts(sum(n_found) if None not in n_found else None, sum(refs) if None not in refs else None),
                 *(_fmt(det.get(k), 3) for k in ("precision", "recall", "f1")),
                 _error_pair(se.get("size_definition")), _error_pair(se.get("sieve"))]
        return [label, *(found if grains else []), MISSING, MISSING,
                "mean |error| " + _three(p["psd_abs_rel_err"], _pct)]

    rows = [photo_row(name, r, r) for name, r in m["photos"].items()]
    rows.append(pooled_row(f"all {len(m['photos'])} (pooled)", m["pooled"], list(m["photos"].values())))
    # the same against the reference grains grown back by half their outline band (photoset outline_band_px)
    restored = [(name, r, r["outlines_restored"]) for name, r in m["photos"].items() if r.get("outlines_restored")]
    rows += [photo_row(f"{name}, outlines restored (band {rest['band_px']:.1f} px)", r, rest)
             for name, r, rest in restored]
    if restored and m.get("pooled_outlines_restored"):
        rows.append(pooled_row(f"all {len(m['photos'])} (pooled), outlines restored", m["pooled_outlines_restored"],
                               [rest for _, _, rest in restored]))
    return head, rows


def photo_sections(photos: dict[str, dict[str, dict]]) -> dict[str, dict]:
    """Per photo set: a line on what it is, and per model its table and what its d-values are of."""
    out: dict[str, dict] = {}
    for arch, per in photos.items():
        for s, m in per.items():
            n = len(m["photos"])
            sec = out.setdefault(s, {"about": (
                f"{n} photo{'s' * (n != 1)}; the reference's grain size: {m['size_definition']}; compared at "
                f"{m['compared_at']}."), "tables": {}})
            what = (f"grains found, their {m['psd_size_definition']}" if m["finds_grains"] else
                    f"finds no grains: its own reading, {m['psd_size_definition']} size")
            # the warnings on its readings (evaluate-photos'), under its table: their d-values are marked ⚠ in it
            warned = [f"⚠ {name}: {r['warning']}" for name, r in m["photos"].items() if r.get("warning")]
            # what its grains not matched are (evaluate-photos' error_kinds), a line per photo under the table
            misses = [f"{name}: {misses_line(r['error_kinds'])}" for name, r in m["photos"].items()
                      if r.get("error_kinds")]
            sec["tables"][arch] = (*photo_table(m), what, warned, misses)
    return out


def misses_line(kinds: dict[str, dict[str, int]]) -> str:
    """A photo's unmatched grains by kind (learn.instances.scoring.error_kinds), in words."""
    fn, fp = kinds["fn"], kinds["fp"]
    return (f"not matched: {sum(fn.values())} reference grains ({', '.join(f'{n} {k}' for k, n in fn.items())}), "
            f"{sum(fp.values())} grains found ({', '.join(f'{n} {k}' for k, n in fp.items())}); "
            "the kinds: docs/photos.md, \"What the misses are\"")


def photo_overlays(photos: dict[str, dict[str, dict]], files: dict[str, dict[str, Path]],
                   fig_dir: Path) -> dict[str, list[tuple[Path, str]]]:
    """The overlays of the models that find grains, copied into the figures: per photo set, (file, caption)."""
    out: dict[str, list[tuple[Path, str]]] = {}
    for arch, per in photos.items():
        for s, m in per.items():
            if not m["finds_grains"]:
                continue
            for name, r in m["photos"].items():
                src = files[arch][s].parent / "overlays" / r["overlay"]
                if not src.is_file():
                    raise PsdError(f"{files[arch][s]} names the overlay {src}, which is not there")
                dst = fig_dir / f"photos_{s}_{arch}_{r['overlay']}"
                copy_file(src, dst)
                out.setdefault(s, []).append((dst, f"{s}/{name}: {arch} — yellow: the grains it found; blue: the "
                                                   "reference grains"))
    return out


def fast_path_rule(bench: dict[str, dict]) -> str:
    budget = next((r["max_r2_change"] for b in bench.values() for r in b["results"]), None)
    cpus = sorted({b["cpu"]["summary"] for b in bench.values() if "cpu" in b})
    skipped = sorted({f"{k} ({why})" for b in bench.values() for r in b["results"] for k, why in r["skipped"].items()})
    text = ("Every inference path worth trying on this machine is timed side by side in one run (median of repeated "
            "runs) and checked on the test split; the fast path (★) is the fastest whose R² of every target "
            f"(d10, d50, d90) stays within ±{budget} of fp32 eager's, chosen by measurement. "
            f"CPU: {'; '.join(cpus) or 'not recorded'}.")
    if skipped:
        text += " Not tried here: " + "; ".join(skipped) + "."
    return text


SPEED_HEAD = ["device", "input (px)", "batch 1 (img/s)", "batched (img/s)", "ms / image (batched)",
              "vs fp32 (batched)", "R² change vs fp32 (the target that moved most)", "parameters (M)", "GFLOPs"]


def _speed_row(arch: str, r: dict, name: str, p: dict) -> list[str]:
    base, change, moved = r["paths"]["fp32"]["batched"]["images_per_s"], p.get("r2_change"), p.get("r2_change_target")
    return [arch, name, r["device"], str(r["input_size"]), _fmt(p["batch1"]["images_per_s"], 1),
            _fmt(p["batched"]["images_per_s"], 1), _fmt(p["batched"]["ms_per_image"], 2),
            f"{p['batched']['images_per_s'] / base:.2f}×",
            MISSING if change is None else f"{change:+.4f}" + (f" ({moved})" if moved else ""),
            _fmt(r["params_m"], 1), _fmt(r["gflops"], 2)]


def speed_table(bench: dict[str, dict]) -> tuple[list[str], list[list[str]]]:
    """One row per model, device and measured path (★: the fast path)."""
    rows = [_speed_row(arch, r, p["name"] + (" ★" if key == r["fast_key"] else ""), p)
            for arch, b in bench.items() for r in b["results"] for key, p in r["paths"].items() if key != "fast"]
    return ["model", "path", *SPEED_HEAD], rows


def fast_speed_table(bench: dict[str, dict]) -> tuple[list[str], list[list[str]]]:
    """One row per model and device: its fast path only (speed_table has every path)."""
    rows = [_speed_row(arch, r, r["paths"]["fast"]["name"], r["paths"]["fast"])
            for arch, b in bench.items() for r in b["results"]]
    return ["model", "fast path", *SPEED_HEAD], rows


def _segmented(metrics: dict[str, dict], datasets: list[str]):
    """(model, dataset, its metrics) of every evaluation with segmentation figures."""
    for arch, m in metrics.items():
        for ds in datasets:
            d = m["datasets"].get(ds)
            if d and "segmentation" in d:
                yield arch, ds, d


def _segmentation_cells(d: dict) -> list[str]:
    """Precision, recall, F1 and the matched grains' median and p90 size error."""
    seg, se = d["segmentation"], d["size_error"]
    matched = se["matched"][se["method"]]
    return [_fmt(seg["precision"], 3), _fmt(seg["recall"], 3), _fmt(seg["f1"], 3),
            MISSING if not matched["n"] else f"{100 * matched['median']:.1f} %",
            MISSING if not matched["n"] else f"{100 * matched['p90']:.1f} %"]


def compact_instance_table(metrics: dict[str, dict], datasets: list[str]) -> tuple[list[str], list[list[str]]]:
    """The instance estimator's segmentation and particle size error per dataset (instance_table
    has the raw R² and every sieve method)."""
    head = ["model", "dataset", "precision", "recall", "F1", "size error median", "size error p90"]
    rows = []
    for arch, ds, d in _segmented(metrics, datasets):
        rows.append([arch, ds, *_segmentation_cells(d)])
    return head, rows


def _md_table(head, rows) -> str:
    """A Markdown table; a "|" inside a cell (e.g. "mean |error|") is escaped, not a column break."""
    def line(cells) -> str:
        return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"

    return "\n".join([line(head), "|" + "---|" * len(head), *map(line, rows)])


_NUMBER = re.compile(r"^([-+−]?[\d.]|—$)")  # a figure (right-aligned), not a name or a text


def _wrap(text: str) -> str:
    """Escaped, with a line-break opportunity after each _ and / (dataset names, paths): long
    names wrap there instead of widening their column or breaking at any letter."""
    return html.escape(text).replace("_", "_<wbr>").replace("/", "/<wbr>")


def _html_table(head, rows, cls: str = "") -> str:
    """A table in its own box: what does not fit scrolls inside it, never the page."""
    h = "".join(f"<th>{_wrap(c)}</th>" for c in head)
    b = "".join("<tr>" + "".join(f"<td>{_wrap(c)}</td>" if _NUMBER.match(c) else f"<td class='t'>{_wrap(c)}</td>"
                                 for c in r) + "</tr>" for r in rows)
    c = f" class='{cls}'" if cls else ""
    return f"<div class='tw'><table{c}><thead><tr>{h}</tr></thead><tbody>{b}</tbody></table></div>"


def _details(summary: str, *body: str) -> str:
    return f"<details><summary>{html.escape(summary)}</summary>{''.join(body)}</details>"


def _png_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's header; None for anything else."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    return None


def _img_tag(path: Path, alt: str, cls: str = "full") -> str:
    """An embedded figure, at most its natural size and at most the page's width (its width and
    height given, so the page's layout does not move as it loads)."""
    raw = Path(path).read_bytes()
    size = _png_size(raw)
    wh = f' width="{size[0]}" height="{size[1]}"' if size else ""
    data = base64.b64encode(raw).decode()
    return (f'<figure class="{cls}"><img alt="{html.escape(alt)}"{wh} src="data:image/png;base64,{data}">'
            f"<figcaption>{_wrap(alt)}</figcaption></figure>")


# The page fits a 1000 px window: at most 1000 px wide, every table in its own box (what cannot
# shrink scrolls there, not the page), long words (dataset names, paths) broken anywhere.
STYLE = ("*{box-sizing:border-box}"
         "body{font-family:system-ui,sans-serif;max-width:1000px;margin:0 auto;padding:0 12px 2em;color:#222;"
         "line-height:1.4;overflow-wrap:break-word}"
         "h1{font-size:1.6em;margin:0.6em 0 0.2em}h2{margin-top:1.4em}"
         ".tw{max-width:100%;overflow-x:auto}"
         "table{border-collapse:collapse;margin:0.6em 0;font-size:13px}"
         "td,th{border:1px solid #ccc;padding:3px 5px;text-align:right;vertical-align:top}"
         "th{background:#f3f3f3;font-weight:600}td.t,td:first-child,th:first-child{text-align:left}"
         ".sub{font-weight:normal;font-size:12px;color:#555}"
         ".card{border:2px solid #4a7bb7;border-radius:8px;background:#f5f9ff;padding:0.2em 1em 0.6em;margin:1em 0}"
         ".card h2{margin:0.5em 0 0.2em;font-size:1.3em}.card table{background:#fff}"
         ".card th[colspan]{text-align:center}table.summary td{white-space:nowrap}"
         "ul.use{margin:0.4em 0;padding-left:1.2em}ul.use li{margin:0.15em 0}"
         ".note{font-size:13px;color:#444;margin:0.3em 0}"
         "img{max-width:100%;height:auto}"
         "figure{margin:0.8em 0}figure.half{display:inline-block;vertical-align:top;width:49%;margin:0.5em 0}"
         "figcaption{font-size:13px;color:#444}"
         "details{margin:0.5em 0}summary{cursor:pointer;color:#245}"
         ".warn{background:#fff3cd;border:1px solid #e0c36a;padding:0.6em 1em}"
         "pre{background:#f7f7f7;padding:1em;font-size:12px;white-space:pre-wrap;overflow-wrap:anywhere}")


# where bench/seed_spread.py writes by default, under the results folder; each run's training params
# beside it in <seed>/<arch>/params.json
SPREAD_JSON = Path("seed_spread") / "spread.json"
RECIPE_FREE = ("seed", "precision", "device")  # what a seed spread may change without being another recipe


def same_recipe(stamp: dict, config: dict, arch: str) -> bool:
    """Whether a seed-spread run's training params (its params.json) are this config's recipe for
    `arch`: equal but for the training seed, the precision and the device."""
    mine = training_recipe(train_params(config, arch))
    return ({k: v for k, v in training_recipe(stamp).items() if k not in RECIPE_FREE}
            == {k: v for k, v in mine.items() if k not in RECIPE_FREE})


def spread_table(spread: dict, runs: Path, config: dict) -> tuple[list[str], list[list[str]], str]:
    """The per-target R² of each model of this config over training seeds (`spread`: a seed_spread
    spread.json; `runs`: its folder, which holds <seed>/<arch>/params.json): mean ± half the range
    per dataset. A model whose runs were trained with another recipe than this config's (or whose
    params are not found) is left out, and the note says so."""
    head = ["model", "dataset", "seeds", *(f"R² {n}" for n in NAMES), "max − min, largest"]
    rows, other = [], []
    seeds = [int(x) for x in spread.get("seeds", [])]
    labels = {ds: d.get("label", ds) for ds, d in (spread.get("datasets") or {}).items()}
    for arch, per in (spread.get("models") or {}).items():
        if arch not in config["train"]["architectures"]:
            continue
        stamps = [runs / str(sd) / arch / "params.json" for sd in seeds]
        if not stamps or not all(f.is_file() and same_recipe(read_json(f), config, arch) for f in stamps):
            other.append(arch)
            continue
        for ds, targets in per.items():
            r2 = [targets.get(n, {}).get("r2", {}) for n in NAMES]
            if not all(_finite(t.get("mean")) for t in r2):
                continue
            widest = max(t.get("max", np.nan) - t.get("min", np.nan) for t in r2)
            rows.append([arch, labels.get(ds, ds), str(max(int(t.get("n", 0)) for t in r2)),
                         *(f"{t['mean']:.2f} ± {t.get('half_range', 0.0):.2f}" for t in r2), f"{widest:.2f}"])
    note = (f"Each model of this config trained with {len(seeds)} seeds ({', '.join(map(str, seeds))}) on the same "
            f"scenes and evaluated on the same test scenes: per-target R² as mean ± half the range, (max − min) / 2, "
            f"measured by bench/seed_spread.py on {spread.get('date', '?')[:10]} ({spread.get('cpu', '?')}, commit "
            f"{spread.get('commit', '?')}). The tables above are of this run's one training seed.")
    if other:
        note += f" Left out, trained with another recipe than this config's: {', '.join(other)}."
    if not spread.get("complete", True):
        note += " The spread was cut short: a row holds the runs it got through."
    return head, rows, note


def paper_tables(config: dict, metrics: dict[str, dict], bench: dict[str, dict], tables: dict,
                 ceilings: dict[str, dict]) -> tuple[tuple, tuple, str]:
    """This run beside the seed paper (paper.py): its Table 2 layout (per-target R² and MAE) for the
    paper's three CNNs and every other model of the run, on the main training dataset's test split,
    with that dataset's visible-particle and sampling ceilings; and its Table 3 layout (images per
    second on the CPU) beside the paper's. The note says what each was measured on."""
    ds = main_training_dataset(config)
    head2 = ["model", "measured", *(f"R² {n}" for n in NAMES), *(f"MAE {n} (mm)" for n in NAMES)]
    rows2 = []
    for arch, m in metrics.items():
        if arch in TABLE2:
            rows2.append([arch, "the paper", *(f"{TABLE2[arch][n][0]:.3f}" for n in NAMES),
                          *(f"{TABLE2[arch][n][2]:.3f}" for n in NAMES)])
        d = m.get("datasets", {}).get(ds)
        if d:
            rows2.append([arch, "this run", *(_fmt(d[n]["r2"], 3) for n in NAMES),
                          *(_fmt(d[n]["mae"], 3) for n in NAMES)])
    ceiling = ceilings.get(ds) or {}
    for kind, what in (("visible", "ceiling: the visible particles' true sizes"), ("sampling", "ceiling: μ and σ")):
        if ceiling.get(kind):
            rows2.append([what, "this run's dataset", *(_fmt(ceiling[kind][f"{n}_mm"], 3) for n in NAMES),
                          *[MISSING] * 3])
    head3 = ["model", "the paper: CPU img/s", "the paper: GPU img/s", "this run: device", "fp32 batch 1 (img/s)",
             "fast path batched (img/s)", "parameters (M)"]
    rows3 = []
    for arch, b in bench.items():
        paper = TABLE3.get(arch, {})
        for r in b["results"]:
            rows3.append([arch, _fmt(paper.get("cpu_fps"), 2), _fmt(paper.get("gpu_fps"), 2), r["device"],
                          _fmt(r["paths"]["fp32"]["batch1"]["images_per_s"], 1),
                          _fmt(r["paths"]["fast"]["batched"]["images_per_s"], 1) + f" ({r['paths']['fast']['name']})",
                          _fmt(r["params_m"], 1)])
    t = tables.get(ds)
    test = np.asarray(t.column("split").to_pylist()) == "test" if t is not None else None
    if test is not None and test.any():
        n = np.asarray(t.column("n_particles"))[test]
        mm = float(np.median(np.asarray(t.column("mm_per_px"))[test]))
        here = (f"{ds}'s {int(test.sum())} test scenes ({n.min()}–{n.max()} particles, {mm:.2f} mm/px, labels of "
                f"{label_kind(t)})")
    else:
        here = f"{ds}'s test scenes"
    cpus = "; ".join(sorted({b["cpu"]["summary"] for b in bench.values() if "cpu" in b})) or "not recorded"
    note = (f"The paper's Table 2 is on {TABLE2_TEST}, its Table 3 on an {TABLE3_GPU} and an {TABLE3_CPU}; this run's "
            f"figures are on {here} and this machine's CPU ({cpus}). Figures compare only where the distributions "
            "match: config/paper-cpu.yaml and config/paper.yaml have the paper's. The ceilings say what a perfect "
            "measurement of this run's images would read.")
    return (head2, rows2), (head3, rows3), note


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

    scatter_figs, curve_figs = [], []
    for a in archs:
        curve = fig_dir / f"loss_{a}.png"
        plot_history(histories[a], a, curve)
        scatter = fig_dir / f"scatter_{a}.png"
        copy_file(inputs.scatters[a], scatter)
        scatter_figs.append((scatter, f"{a}: predicted vs true"))
        curve_figs.append((curve, f"{a}: training and validation loss"))

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
    fast_head, fast_rows = fast_speed_table(bench)
    photos = {a: {s: read_json(f) for s, f in inputs.photos.get(a, {}).items()} for a in archs if a in inputs.photos}
    for a, per in photos.items():
        for s, m in per.items():
            if (m.get("arch"), m.get("photoset")) != (a, s):
                raise PsdError(f"{inputs.photos[a][s]} holds {m.get('arch')!r} on {m.get('photoset')!r}, not {a!r} on "
                               f"{s!r}")
    photo_figs = photo_overlays(photos, inputs.photos, fig_dir)
    summ = summarize(config, metrics, bench, tables, photos)
    cfg_yaml = yaml.safe_dump(config, sort_keys=False)
    when = dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    ceilings = {ds: read_json(f) for ds, f in inputs.ceilings.items()}
    tested = evaluation_datasets(config)  # not the datasets of training scenes only
    tested += [c.dataset for c in summ.columns if c.dataset not in tested]  # and any other evaluated one
    where = {c.dataset: f"{c.renderer}, {c.split}" for c in summ.columns}
    acc = {ds: accuracy_table(metrics, ds, ceilings.get(ds), rerenders_of(config, ds)) for ds in tested}
    compact = {ds: compact_accuracy_table(metrics, ds, ceilings.get(ds)) for ds in tested}
    inst_head, inst_rows = instance_table(metrics, tested)
    inst_compact = compact_instance_table(metrics, tested)
    paper2, paper3, paper_note = paper_tables(config, metrics, bench, tables, ceilings)
    spread_head, spread_rows, spread_note = ([], [], "") if inputs.spread is None else \
        spread_table(read_json(inputs.spread), inputs.spread.parent, config)

    md = ["# psdfactory report", "", "## Summary: which model, how good, how fast", "",
          _md_table(*summary_table(summ)), ""]
    md += [f"- **{a}**: {u}" for a, u in summ.use.items()] + ["", summ.note, ""]
    if warning:
        md += [f"> **Warning:** {warning}", ""]
    md += [f"Generated {when} by psdfactory {__version__}.", ""]
    md += ["## Datasets", "", _md_table(count_head, count_rows), ""]
    if compare_rows:
        md += ["Render backends compared on the same settled poses "
               f"({summary['resolution']} px, Cycles at {summary['cycles'].get('samples', '?')} samples):", "",
               _md_table(compare_head, compare_rows), ""]
    md += [f"![{c}](figures/{p.name})" for p, c in figures] + [""]
    md += ["## Accuracy", "", ACCURACY_NOTE, ""]
    for ds in tested:
        md += [f"### {ds} ({where.get(ds, renderer_of(config, ds))})", "", _md_table(*compact[ds]), "",
               "All figures:", "", _md_table(*acc[ds]), ""]
    if spread_rows:
        md += ["### Over training seeds", "", spread_note, "", _md_table(spread_head, spread_rows), ""]
    if paper2[1]:
        md += ["### Beside the paper (its Tables 2 and 3)", "", paper_note, "", _md_table(*paper2), "",
               _md_table(*paper3), ""]
    for s, models in photo_sections(photos).items():
        md += [f"## Photos: {s}", "", models["about"], "", PHOTOS_NOTE, ""]
        for a, (head, rows, what, warned, misses) in models["tables"].items():
            md += [f"### {a} ({what})", "", _md_table(head, rows), "", *(f"{w}  " for w in (*warned, *misses)), ""]
        md += [f"![{c}](figures/{p.name})" for p, c in photo_figs.get(s, [])] + [""]
    if inst_rows:
        md += ["## Instance estimator", "", INSTANCE_NOTE, "", _md_table(*inst_compact), "",
               "All figures:", "", _md_table(inst_head, inst_rows), ""]
    md += ["## Inference speed", "", fast_path_rule(bench), "", _md_table(fast_head, fast_rows), "",
           "Every path measured:", "", _md_table(speed_head, speed_rows), ""]
    md += [f"![{c}](figures/{p.name})" for p, c in scatter_figs + curve_figs] + [""]
    md += ["## Weights used", "", _md_table(["CNN model", "weights"], weights), ""]
    md += ["## Configuration", "", "```yaml", cfg_yaml.rstrip(), "```", ""]
    with atomic_path(out_md) as tmp:
        tmp.write_text("\n".join(md))

    e = html.escape
    h = [f"<!doctype html><html lang='en'><head><meta charset='utf-8'>"
         "<meta name='viewport' content='width=device-width, initial-scale=1'><title>psdfactory report</title>"
         f"<style>{STYLE}</style></head><body>", "<h1>psdfactory report</h1>", summary_html(summ, warning),
         f"<p class='note'>Generated {when} by psdfactory {__version__}.</p>"]
    h += ["<h2>Datasets</h2>", _html_table(count_head, count_rows)]
    if compare_rows:
        h += [f"<p>Render backends compared on the same settled poses ({summary['resolution']} px, Cycles at "
              f"{summary['cycles'].get('samples', '?')} samples):</p>", _html_table(compare_head, compare_rows)]
    h += [_img_tag(p, c) for p, c in figures]
    h += ["<h2>Accuracy</h2>", f"<p>{e(ACCURACY_NOTE)}</p>"]
    for ds in tested:
        h += [f"<h3>{_wrap(ds)} <span class='sub'>({e(where.get(ds, renderer_of(config, ds)))})</span></h3>",
              _html_table(*compact[ds]),
              _details(f"All figures on {ds}: R² on re-renders, relative error, pooled, order violations",
                       _html_table(*acc[ds]))]
    if spread_rows:
        h += ["<h3>Over training seeds</h3>", f"<p class='note'>{e(spread_note)}</p>",
              _html_table(spread_head, spread_rows)]
    if paper2[1]:
        h += ["<h3>Beside the paper <span class='sub'>(its Tables 2 and 3)</span></h3>",
              f"<p class='note'>{e(paper_note)}</p>", _html_table(*paper2), _html_table(*paper3)]
    for s, models in photo_sections(photos).items():
        h += [f"<h2>Photos: {_wrap(s)}</h2>", f"<p>{e(models['about'])}</p>", f"<p class='note'>{e(PHOTOS_NOTE)}</p>"]
        for a, (head, rows, what, warned, misses) in models["tables"].items():
            h += [f"<h3>{_wrap(a)} <span class='sub'>({e(what)})</span></h3>", _html_table(head, rows),
                  *(f"<p class='note'>{e(w)}</p>" for w in (*warned, *misses))]
        h += [_img_tag(p, c) for p, c in photo_figs.get(s, [])]
    if inst_rows:
        h += ["<h2>Instance estimator</h2>", f"<p>{e(INSTANCE_NOTE)}</p>", _html_table(*inst_compact),
              _details("All figures: calibrated and raw R², size errors of fully visible particles per method",
                       _html_table(inst_head, inst_rows))]
    h += ["<h2>Inference speed</h2>", f"<p>{e(fast_path_rule(bench))}</p>", _html_table(fast_head, fast_rows),
          _details("Every path measured", _html_table(speed_head, speed_rows))]
    h += [_img_tag(p, c) for p, c in scatter_figs]
    h += [_img_tag(p, c, "half") for p, c in curve_figs]
    h += ["<h2>Weights used</h2>", _html_table(["CNN model", "weights"], weights)]
    h += ["<h2>Configuration</h2>", _details("The configuration of this run (YAML)", f"<pre>{e(cfg_yaml)}</pre>"),
          "</body></html>"]
    with atomic_path(out_html) as tmp:
        tmp.write_text("\n".join(h))
