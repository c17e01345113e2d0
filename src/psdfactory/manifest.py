"""Gather per-scene labels into sharded Parquet manifests.

``<results>/<dataset>/manifest/scenes/shard-NNNNN.parquet``: one row per scene.
``<results>/<dataset>/manifest/particles/shard-NNNNN.parquet``: one row per particle.
Shard k holds scenes k*shard_size … (k+1)*shard_size-1, so adding scenes rewrites only the
last shard and the new ones. Image paths are relative to the results root.
Read a whole table with ``pyarrow.parquet.read_table('<results>/<dataset>/manifest/scenes')``.
"""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa

from . import PsdError
from .io import read_json, read_parquet, write_parquet
from .psd import ALL_DEFINITION_TARGETS, SIZE_DEFINITIONS, TARGETS, VOLUME_TARGETS, size_column
from .seeding import assign_split

SCENE_SCHEMA = pa.schema(
    [
        ("scene_id", pa.string()),
        ("dataset", pa.string()),
        ("index", pa.int64()),
        ("split", pa.string()),
        ("image_path", pa.string()),
        ("mask_path", pa.string()),
        ("mm_per_px", pa.float64()),
        ("resolution", pa.int32()),
        ("n_particles", pa.int32()),
        ("n_visible", pa.int32()),
        ("covered_fraction", pa.float64()),
        ("size_definition", pa.string()),  # what d*_mm and d*_v_mm are percentiles of
        ("weighting", pa.string()),  # what d*_mm count: number (particles) or volume
        *((t, pa.float64()) for t in TARGETS + VOLUME_TARGETS),
        *((t, pa.float64()) for t in ALL_DEFINITION_TARGETS),  # every definition, e.g. d50_sieve_mm, d50_esd_v_mm
        ("shape_type", pa.string()),
        ("size_mean", pa.float64()),
        ("size_sigma", pa.float64()),
        ("table_size_mm", pa.float64()),
        ("render_backend", pa.string()),
        ("settled_fraction", pa.float64()),
        ("worst_penetration_mm", pa.float64()),
        ("sim_attempts", pa.int32()),
        ("config_hash", pa.string()),
        ("psd_size_mm", pa.list_(pa.float64())),
        ("psd_q0", pa.list_(pa.float64())),
        ("psd_q3", pa.list_(pa.float64())),
    ]
)

PARTICLE_COLUMNS = ("scene_id", "particle_id", "size_mm", "volume_mm3", "x_mm", "y_mm", "z_mm", "visible_px",
                    *(size_column(d) for d in SIZE_DEFINITIONS))


def shard_name(k: int) -> str:
    return f"shard-{k:05d}.parquet"


def build_shard(scene_dirs: list[Path], results_root: Path, fractions: dict[str, float]) -> tuple[pa.Table, pa.Table]:
    rows, particles = [], []
    results_root = Path(results_root).resolve()
    for d in map(Path, scene_dirs):
        rec = read_json(d / "labels.json")
        spec = read_json(d / "spec.json")
        for f in ("image.png", "mask.png"):
            if not (d / f).is_file():
                raise PsdError(f"missing {d / f}; rerun the render job of {rec['scene_id']}")
        rel = d.resolve().relative_to(results_root)
        if "size_definition" not in rec:
            raise PsdError(f"{d / 'labels.json'} predates named size definitions; rerun the label job of "
                           f"{rec.get('scene_id', d.name)}")
        row = {k: rec.get(k) for k in SCENE_SCHEMA.names}
        row.update(
            split=assign_split(spec["entropy"], fractions),
            image_path=str(rel / "image.png"),
            mask_path=str(rel / "mask.png"),
        )
        rows.append(row)
        pt = read_parquet(d / "particles.parquet")
        missing = [c for c in PARTICLE_COLUMNS if c not in pt.column_names]
        if missing:
            raise PsdError(f"{d / 'particles.parquet'} lacks columns {missing}; rerun the label job")
        particles.append(pt)
    scenes = pa.Table.from_pylist(rows, schema=SCENE_SCHEMA)
    parts = pa.concat_tables(particles) if particles else pa.table({c: [] for c in PARTICLE_COLUMNS})
    return scenes, parts


def write_shard(scene_dirs: list[Path], results_root: Path, fractions: dict[str, float], scenes_out: Path,
                particles_out: Path) -> pa.Table:
    scenes, parts = build_shard(scene_dirs, results_root, fractions)
    write_parquet(particles_out, parts)
    write_parquet(scenes_out, scenes)
    return scenes


def read_shards(paths: list[Path]) -> pa.Table:
    """The scene tables of these shard files (of any datasets) as one table."""
    if not paths:
        raise PsdError("no manifest shards given")
    return pa.concat_tables([read_parquet(p) for p in paths])


def read_scenes(results_root: Path, dataset: str) -> pa.Table:
    path = Path(results_root) / dataset / "manifest" / "scenes"
    if not path.is_dir() or not any(path.glob("*.parquet")):
        raise PsdError(f"no manifest at {path}; run the workflow first (snakemake -j2)")
    import pyarrow.parquet as pq

    return pq.read_table(path)


def group_by_scene(table: pa.Table, columns: list[str] | tuple[str, ...]) -> dict:
    """scene_id → {column: numpy array of that scene's rows} of a particle table."""
    import numpy as np

    ids = np.asarray(table.column("scene_id").to_pylist())
    cols = {k: np.asarray(table.column(k)) for k in columns}
    order = np.argsort(ids, kind="stable")
    uniq, start = np.unique(ids[order], return_index=True)
    return {str(u): {k: v[g] for k, v in cols.items()} for u, g in zip(uniq, np.split(order, start[1:]), strict=True)}


PARTICLE_READ_COLUMNS = ("particle_id", "size_mm", "z_mm")  # what training and evaluation read of a particle


def read_particles(results_root: Path, dataset: str, columns: tuple[str, ...] = PARTICLE_READ_COLUMNS) -> dict:
    """scene_id → {column: array} from a dataset's particle manifest."""
    import pyarrow.parquet as pq

    path = Path(results_root) / dataset / "manifest" / "particles"
    if not path.is_dir():
        raise PsdError(f"no particle manifest at {path}")
    return group_by_scene(pq.read_table(path, columns=["scene_id", *columns]), columns)
