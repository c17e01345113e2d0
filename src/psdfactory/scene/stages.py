"""The per-scene stages as file-to-file steps: each reads its inputs from a scene folder,
calls the pure functions of its module and writes its outputs atomically.

Scene folder ``<results>/<dataset>/scenes/<scene_id>/``:
  sample   → spec.json, geometry.npz
  simulate → poses.parquet, simulate.json
  render   → image.png, mask.png, render.json
  label    → labels.json, particles.parquet
  stages/<stage>.json: the params each stage last ran with (written after its outputs)

``run_scenes`` runs one stage over many scene folders: the Snakemake rules call it with one
folder (one job per scene) or a batch of folders, skipping the scenes that are up to date.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import PsdError
from ..io import (
    DiskFullError,
    column_array,
    copy_file,
    read_json,
    read_npz,
    read_parquet,
    read_png,
    table_from_columns,
    write_json,
    write_npz,
    write_parquet,
    write_png,
)
from ..seeding import scene_id, scene_index
from .geometry import Geometry

logger = logging.getLogger(__name__)
POSE_COLUMNS = ("particle_id", "x_mm", "y_mm", "z_mm", "qx", "qy", "qz", "qw", "settled")


def load_geometry(scene_dir: Path) -> Geometry:
    return Geometry.from_arrays(read_npz(scene_dir / "geometry.npz"))


def load_poses(scene_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = read_parquet(scene_dir / "poses.parquet")
    missing = [c for c in POSE_COLUMNS if c not in t.column_names]
    if missing:
        raise PsdError(f"{scene_dir / 'poses.parquet'} lacks columns {missing}; rerun simulate")

    def col(name: str) -> np.ndarray:
        return column_array(t, name)

    pos = np.stack([col("x_mm"), col("y_mm"), col("z_mm")], axis=1)
    quat = np.stack([col("qx"), col("qy"), col("qz"), col("qw")], axis=1)
    return pos, quat, col("settled")


def source_dir(scene_dir: Path, dataset: str, index: int) -> Path:
    """The folder of scene `index` of `dataset` beside a scene folder (same results root)."""
    return Path(scene_dir).parent.parent.parent / dataset / "scenes" / scene_id(dataset, index)


def source_inputs(stage: str, params: dict, scene_dir: Path) -> list[Path]:
    """The files of another dataset that a re-rendered scene's stage copies (its inputs too)."""
    if stage == "sample" and "source" in params:
        src = source_dir(scene_dir, params["source"]["dataset"], params["source"]["index"])
        return [src / "spec.json", src / "geometry.npz"]
    if stage == "simulate" and params.get("copy_from_source"):
        s = read_json(Path(scene_dir) / "spec.json")["source"]
        src = source_dir(scene_dir, s["dataset"], s["index"])
        return [src / "poses.parquet", src / "simulate.json"]
    return []


def adopt_source(stage: str, params: dict, scene_dir: Path) -> dict:
    """A re-rendered scene takes its particles (sample) or settled poses (simulate) from its
    source scene, byte for byte; only its spec names it as itself, keeping the source's random
    streams (so the look drawn for the render is the source's too)."""
    files = source_inputs(stage, params, scene_dir)
    missing = [f for f in files if not f.is_file()]
    if missing:
        raise PsdError(f"{scene_dir.name} re-renders {missing[0].parent.name}, which lacks {missing[0].name}; "
                       "run the source dataset's stages first")
    (meta,) = [f for f in files if f.suffix == ".json"]
    for f in files:
        if f is not meta:
            copy_file(f, scene_dir / f.name)
    record = read_json(meta)
    if stage == "sample":
        src = params["source"]
        record.update(dataset=params["dataset"], index=params["index"], scene_id=scene_dir.name,
                      source={"dataset": src["dataset"], "index": src["index"], "scene_id": record["scene_id"]})
    else:
        record["scene_id"] = scene_dir.name
    write_json(scene_dir / meta.name, record)  # last: marks the stage complete
    logger.info(f"{stage}: {scene_dir.name} takes its {'particles' if stage == 'sample' else 'settled poses'} from "
        f"{meta.parent.name} (a re-render)")
    return record


def run_sample(params: dict, scene_dir: Path) -> dict:
    from .sampling import SampleParams, sample_scene

    if "source" in params:
        return adopt_source("sample", params, scene_dir)
    t0 = time.perf_counter()
    spec, geometry = sample_scene(SampleParams.from_dict(params))
    write_npz(scene_dir / "geometry.npz", **geometry)
    write_json(scene_dir / "spec.json", spec)  # last: spec.json marks the stage complete
    logger.info(f"sampled {spec['scene_id']}: {spec['samplesize']} {spec['shape_type']} particles, "
        f"mean {spec['size_mean']:.2f} mm, sigma {spec['size_sigma']:.2f} mm ({time.perf_counter() - t0:.2f} s)")
    return spec


def run_simulate(params: dict, scene_dir: Path) -> dict:
    from .physics import PhysicsParams, simulate

    if params.get("copy_from_source"):
        return adopt_source("simulate", params, scene_dir)
    spec = read_json(scene_dir / "spec.json")
    geometry = load_geometry(scene_dir)
    if len(geometry) != spec["samplesize"]:
        raise PsdError(f"{scene_dir}: spec.json and geometry.npz disagree on the particle count; rerun sample")
    xy = np.array([[q["x"], q["y"]] for q in spec["particles"]], dtype=float).reshape(-1, 2)
    res = simulate(geometry, xy, float(spec["table_size"]), spec["entropy"], PhysicsParams.from_dict(params))
    n = len(geometry)
    table = table_from_columns(
        {
            "particle_id": np.arange(n, dtype=np.int32),
            "x_mm": res.positions_mm[:, 0],
            "y_mm": res.positions_mm[:, 1],
            "z_mm": res.positions_mm[:, 2],
            "qx": res.quaternions[:, 0],
            "qy": res.quaternions[:, 1],
            "qz": res.quaternions[:, 2],
            "qw": res.quaternions[:, 3],
            "settled": res.settled,
        }
    )
    write_parquet(scene_dir / "poses.parquet", table)
    write_json(scene_dir / "simulate.json", {"scene_id": spec["scene_id"], **res.quality})
    q = res.quality
    logger.info(f"simulated {spec['scene_id']}: settled {q['settled_fraction']:.3f}, worst penetration "
        f"{q['worst_penetration_mm']:.2f} mm, attempt {res.attempt}, {q['wall_s']:.1f} s")
    return q


def run_render(params: dict, scene_dir: Path) -> dict:
    from .render import RenderParams, render_scene

    t0 = time.perf_counter()
    spec = read_json(scene_dir / "spec.json")
    geometry = load_geometry(scene_dir)
    pos, quat, _ = load_poses(scene_dir)
    image, mask, meta = render_scene(spec, geometry, pos, quat, RenderParams.from_dict(params), spec["entropy"])
    write_png(scene_dir / "image.png", image)
    write_png(scene_dir / "mask.png", mask)
    write_json(scene_dir / "render.json", {"scene_id": spec["scene_id"], **meta})
    logger.info(f"rendered {spec['scene_id']}: {meta['resolution']} px, {meta['mm_per_px']:.4f} mm/px, "
        f"{len(np.unique(mask)) - 1} particles visible ({time.perf_counter() - t0:.2f} s)")
    return meta


def run_label(params: dict, scene_dir: Path) -> dict:
    from ..psd import SIZE_DEFINITIONS, size_column
    from .labels import LabelParams, in_view, scene_labels, visible_pixels
    from .sizes import equivalent_sphere_diameter, footprints

    spec = read_json(scene_dir / "spec.json")
    sim = read_json(scene_dir / "simulate.json")
    rend = read_json(scene_dir / "render.json")
    geometry = load_geometry(scene_dir)
    pos, quat, settled = load_poses(scene_dir)
    mask = read_png(scene_dir / "mask.png")
    if mask.ndim != 2 or mask.shape != (rend["resolution"], rend["resolution"]):
        raise PsdError(f"{scene_dir / 'mask.png'} is not a {rend['resolution']}² 16-bit mask; rerun render")
    n = len(geometry)
    vis = visible_pixels(mask, n)
    lp = LabelParams.from_dict(params)
    by_column = {
        "sieve_mm": geometry.sieve_mm, "a_axis_mm": geometry.dims_mm[:, 0], "b_axis_mm": geometry.dims_mm[:, 1],
        "c_axis_mm": geometry.dims_mm[:, 2], "esd_mm": equivalent_sphere_diameter(geometry.volume_mm3),
        # every built-in family is convex: all silhouettes at once; a user's mesh: one hull each
        **footprints(geometry.vertices, geometry.vert_offsets, quat,
                     *((geometry.faces, geometry.face_offsets) if spec["shape_type"] != "mesh" else ())),
    }
    by_definition = {d: by_column[size_column(d)] for d in SIZE_DEFINITIONS}
    # the particles the labels count: those whose centre the camera sees (a view of mm_per_px * resolution), or all
    view_mm = float(rend["mm_per_px"]) * int(rend["resolution"])
    counted = in_view(pos[:, 0], pos[:, 1], view_mm) if lp.particles == "in_view" else None
    labels = scene_labels(by_definition, geometry.volume_mm3, vis, mask.size, tuple(spec["size_bounds"]), lp, counted)
    record = {
        "scene_id": spec["scene_id"],
        "dataset": spec["dataset"],
        "index": spec["index"],
        "shape_type": spec["shape_type"],
        "size_mean": spec["size_mean"],
        "size_sigma": spec["size_sigma"],
        "table_size_mm": float(spec["table_size"]),
        "config_hash": spec["config_hash"],
        "mm_per_px": rend["mm_per_px"],
        "resolution": rend["resolution"],
        "render_backend": rend["backend"],
        "settled_fraction": sim["settled_fraction"],
        "worst_penetration_mm": sim["worst_penetration_mm"],
        "sim_attempts": sim["attempt"] + 1,
        **labels,
    }
    particles = table_from_columns(
        {
            "scene_id": np.full(n, spec["scene_id"]),
            "particle_id": np.arange(n, dtype=np.int32),
            "size_mm": by_definition[lp.size_definition],  # the labels' definition (size_definition)
            **by_column,
            "volume_mm3": geometry.volume_mm3,
            "x_mm": pos[:, 0],
            "y_mm": pos[:, 1],
            "z_mm": pos[:, 2],
            "visible_px": vis.astype(np.int64),
            "settled": settled,
        }
    )
    write_parquet(scene_dir / "particles.parquet", particles)
    write_json(scene_dir / "labels.json", record)
    logger.info(f"labelled {spec['scene_id']}: {lp.size_definition} d10/d50/d90 = {record['d10_mm']:.2f}/"
        f"{record['d50_mm']:.2f}/{record['d90_mm']:.2f} mm ({lp.weighting}), {record['d10_v_mm']:.2f}/"
        f"{record['d50_v_mm']:.2f}/{record['d90_v_mm']:.2f} mm (volume) of {record['n_particles']} particles "
        f"({lp.particles}); {record['n_visible']}/{n} visible")
    return record


# ---- stages over many scenes -----------------------------------------------------------------

@dataclass(frozen=True)
class Stage:
    name: str
    run: Callable[[dict, Path], object]
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]


STAGES = {
    s.name: s
    for s in (
        Stage("sample", run_sample, (), ("spec.json", "geometry.npz")),
        Stage("simulate", run_simulate, ("spec.json", "geometry.npz"), ("poses.parquet", "simulate.json")),
        Stage("render", run_render, ("spec.json", "geometry.npz", "poses.parquet"),
              ("image.png", "mask.png", "render.json")),
        Stage("label", run_label,
              ("spec.json", "geometry.npz", "poses.parquet", "simulate.json", "mask.png", "render.json"),
              ("labels.json", "particles.parquet")),
    )
}
SCENE_FILES = tuple(f for s in STAGES.values() for f in s.outputs)


def missing_scene_files(scenes_root: str, scene_ids: list[str]) -> list[str]:
    """Paths of the scene files missing from those scene folders that exist (deleted by hand).
    One listing of the scenes folder and one of each scene folder that exists — not a stat per
    file — so a 10,000-scene dataset is checked in a fraction of a second, changing nothing."""
    import os

    try:
        present = set(os.listdir(scenes_root))
    except (FileNotFoundError, NotADirectoryError):
        return []
    missing = []
    for sid in scene_ids:
        if sid in present:
            d = f"{scenes_root}/{sid}"
            try:
                have = set(os.listdir(d))
            except NotADirectoryError:
                continue
            missing += [f"{d}/{f}" for f in SCENE_FILES if f not in have]
    return missing


def record_path(scene_dir: Path, stage: str) -> Path:
    return Path(scene_dir) / "stages" / f"{stage}.json"


def scene_params(stage: str, params: dict, scene_dir: Path) -> dict:
    """The params of one scene: `sample` takes its scene index from the folder name."""
    if stage != "sample":
        return params
    scene_dir = Path(scene_dir)
    dataset = params.get("dataset")
    if dataset is not None and not scene_dir.name.startswith(f"{dataset}-"):
        raise PsdError(f"{scene_dir}: folder name does not belong to dataset {dataset!r}")
    try:
        index = scene_index(scene_dir.name)
    except ValueError as e:
        raise PsdError(f"{scene_dir}: {e}") from None
    if "indices" in params.get("source", {}):
        from ..config import rerender_scene_params

        return rerender_scene_params(params, index)
    return {**params, "index": index}


def _canonical(params: dict) -> str:
    return json.dumps(params, sort_keys=True, separators=(",", ":"))


def up_to_date(stage: str, params: dict, scene_dir: Path) -> bool:
    """Make's rule, per scene: the stage's outputs exist, it last ran with these params and no
    input changed since (the record is written after the outputs, so it is the newest)."""
    st, scene_dir = STAGES[stage], Path(scene_dir)
    rec = record_path(scene_dir, stage)
    try:
        done = rec.stat().st_mtime_ns
        if any(not (scene_dir / f).is_file() for f in st.outputs):
            return False
        inputs = [scene_dir / f for f in st.inputs] + source_inputs(stage, params, scene_dir)
        if any(f.stat().st_mtime_ns > done for f in inputs):
            return False
        return json.loads(rec.read_text()).get("params") == json.loads(_canonical(params))
    except (OSError, ValueError):
        return False


def run_stage(stage: str, params: dict, scene_dir: Path) -> None:
    """Run one stage on one scene folder and record the params it ran with."""
    from ..io import write_json

    scene_dir = Path(scene_dir)
    p = scene_params(stage, params, scene_dir)
    missing = [f for f in STAGES[stage].inputs if not (scene_dir / f).is_file()]
    if missing:
        raise PsdError(f"{scene_dir}: missing {', '.join(missing)}; run the stages before {stage} first")
    scene_dir.mkdir(parents=True, exist_ok=True)
    STAGES[stage].run(p, scene_dir)
    write_json(record_path(scene_dir, stage), {"stage": stage, "params": json.loads(_canonical(p))})


def _run_one(args: tuple[str, dict, str]) -> tuple[str, float, str | None]:
    stage, params, scene_dir = args
    t0 = time.perf_counter()
    try:
        run_stage(stage, params, Path(scene_dir))
    except DiskFullError:
        raise  # every other scene would fail the same way: stop the batch
    except PsdError as e:
        return scene_dir, time.perf_counter() - t0, str(e)
    return scene_dir, time.perf_counter() - t0, None


def run_scenes(stage: str, params: dict, scene_dirs: list[Path], skip_up_to_date: bool = False,
               jobs: int = 1, stamp: Path | None = None) -> dict:
    """Run `stage` over scene folders (in `jobs` processes), optionally skipping those up to
    date; print progress with rate and ETA; write a summary `stamp` only if every scene succeeded.
    """
    if stage not in STAGES:
        raise PsdError(f"unknown stage {stage!r}; one of {', '.join(STAGES)}")
    dirs = [Path(d) for d in scene_dirs]
    todo = [d for d in dirs if not (skip_up_to_date and up_to_date(stage, scene_params(stage, params, d), d))]
    if skip_up_to_date:
        logger.info(f"{stage}: {len(todo)} of {len(dirs)} scenes to run, {len(dirs) - len(todo)} up to date")
    t0 = time.perf_counter()
    failed: list[str] = []
    work = [(stage, params, str(d)) for d in todo]
    jobs = max(1, min(int(jobs), len(work)))
    if stage == "render" and params.get("backend") == "cycles" and jobs > 1:
        logger.info(f"render: Cycles uses every core (or the GPU) itself, so the {len(work)} scenes run one at a time")
        jobs = 1
    pool = None
    if jobs == 1:
        results = map(_run_one, work)
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed

        # fork: the stages import no threads-holding libraries (no torch), and start-up is free
        pool = ProcessPoolExecutor(jobs, mp_context=mp.get_context("fork"))
        results = (f.result() for f in as_completed([pool.submit(_run_one, w) for w in work]))
    try:
        for k, (d, _, err) in enumerate(results, 1):
            if err:
                failed.append(f"{d}: {err}")
                logger.error(f"{stage}: FAILED {d}: {err}")
            if len(work) > 1:
                el = time.perf_counter() - t0
                logger.info(f"{stage}: {k}/{len(work)} scenes, {k / el:.2f} scenes/s, "
                            f"ETA {(len(work) - k) * el / k:.0f} s")
    except Exception as e:  # a worker killed (out of memory, a crash in a native library)
        from concurrent.futures.process import BrokenProcessPool

        if isinstance(e, BrokenProcessPool):
            raise PsdError(f"{stage}: a worker process died (out of memory? a crash in pybullet or Blender?) "
                           f"after {len(failed)} failures; finished scenes are kept and skipped on a rerun") from None
        raise
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    if failed and len(work) == 1:
        raise PsdError(failed[0])
    if failed:
        raise PsdError(f"{stage} failed for {len(failed)} of {len(work)} scenes (the others are kept and "
                       "will be skipped on a rerun):\n  " + "\n  ".join(failed))
    summary = {"stage": stage, "scenes": [d.name for d in dirs], "ran": [d.name for d in todo],
               "seconds": round(time.perf_counter() - t0, 3)}
    if stamp is not None:
        from ..io import write_json

        write_json(stamp, summary)
    return summary
