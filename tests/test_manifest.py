import numpy as np
import pyarrow.parquet as pq
import pytest

from psdfactory import PsdError
from psdfactory.manifest import SCENE_SCHEMA, assign_split, build_shard, write_shard

REQUIRED_SCENE = [
    "scene_id", "dataset", "split", "image_path", "mask_path", "mm_per_px", "n_particles", "n_visible",
    "d10_mm", "d50_mm", "d90_mm", "d10_v_mm", "d50_v_mm", "d90_v_mm",
]
REQUIRED_PARTICLE = ["scene_id", "particle_id", "size_mm", "volume_mm3", "x_mm", "y_mm", "z_mm", "visible_px"]


def test_split_is_deterministic_and_follows_fractions():
    fr = {"train": 0.7, "val": 0.2, "test": 0.1}
    splits = [assign_split([1, 2, i], fr) for i in range(5000)]
    assert splits == [assign_split([1, 2, i], fr) for i in range(5000)]
    counts = {s: splits.count(s) / 5000 for s in fr}
    for s, f in fr.items():
        assert abs(counts[s] - f) < 0.03
    assert assign_split([1, 2, 3], {"test": 1.0}) == "test"


@pytest.mark.slow
def test_manifest_schema_and_paths(tiny_results, tmp_path):
    _, root = tiny_results
    dirs = sorted((root / "tiny" / "scenes").iterdir())
    out_s, out_p = tmp_path / "scenes" / "shard-00000.parquet", tmp_path / "particles" / "shard-00000.parquet"
    write_shard(dirs, root, {"train": 1.0}, out_s, out_p)
    scenes, parts = pq.read_table(out_s), pq.read_table(out_p)
    assert scenes.schema == SCENE_SCHEMA
    assert set(REQUIRED_SCENE) <= set(scenes.column_names)
    assert set(REQUIRED_PARTICLE) <= set(parts.column_names)
    assert scenes.num_rows == 3
    assert parts.num_rows == sum(scenes.column("n_particles").to_pylist())
    for row in scenes.to_pylist():
        assert not row["image_path"].startswith("/")
        assert (root / row["image_path"]).is_file() and (root / row["mask_path"]).is_file()
        assert row["d10_mm"] <= row["d50_mm"] <= row["d90_mm"]
        assert row["split"] == "train"
        sub = parts.filter(np.array(parts.column("scene_id").to_pylist()) == row["scene_id"])
        assert (np.array(sub.column("visible_px")) > 0).sum() == row["n_visible"]
        sizes = np.array(sub.column("size_mm"))
        assert row["d50_mm"] == pytest.approx(np.percentile(sizes, 50, method="hazen"))


@pytest.mark.slow
def test_labels_are_reproducible(tiny_results, tmp_path):
    from psdfactory.io import read_json

    from .conftest import make_scene

    cfg, root = tiny_results
    again = make_scene(cfg, tmp_path / "tiny-000000", index=0)
    a = read_json(root / "tiny" / "scenes" / "tiny-000000" / "labels.json")
    b = read_json(again / "labels.json")
    assert a == b


def test_missing_scene_files_are_named(tmp_path):
    with pytest.raises(PsdError, match="missing file"):
        build_shard([tmp_path / "nope"], tmp_path, {"train": 1.0})


def test_column_array_reads_parquet_columns_as_pyarrow_does(tmp_path):
    """io.column_array (the scene jobs' reader of a pose table) gives pyarrow's own to_numpy values and
    dtypes for every column kind a scene file holds, over chunk borders and sliced tables."""
    import pyarrow as pa

    from psdfactory.io import column_array, read_parquet, write_parquet

    rng = np.random.default_rng(3)
    t = pa.table({
        "x": pa.chunked_array([rng.normal(size=7), rng.normal(size=13)]),
        "f": pa.array(rng.normal(size=20).astype(np.float32)),
        "i": pa.chunked_array([np.arange(11, dtype=np.int32), np.arange(9, dtype=np.int32)]),
        "settled": pa.chunked_array([rng.random(9) > 0.5, rng.random(11) > 0.5]),
        "name": pa.array([f"p{i}" for i in range(20)]),
        "gap": pa.array([1.0, None] * 10),
    })
    write_parquet(tmp_path / "t.parquet", t)
    for table in (t, t.slice(3), t.slice(9, 8), read_parquet(tmp_path / "t.parquet")):
        for name in ("x", "f", "i", "settled"):
            got, want = column_array(table, name), table.column(name).to_numpy()
            assert got.dtype == want.dtype and np.array_equal(got, want), name
            assert got.flags.writeable  # a copy, not a read-only view of the table's buffer
        assert list(column_array(table, "name")) == table.column("name").to_pylist()  # falls back
        assert np.array_equal(column_array(table, "gap"), table.column("gap").to_numpy(), equal_nan=True)
    assert column_array(t.slice(20), "settled").shape == (0,)


def test_table_from_columns_builds_what_pyarrow_table_builds(tmp_path):
    """io.table_from_columns (the scene jobs' writer of pose and particle tables) gives pa.table's own
    types and values, and the same Parquet bytes, for every column kind a scene file holds: numbers of
    each width, strided and byte-swapped arrays, booleans of any length, strings (empty and not ASCII
    too); other columns go through pa.array."""
    import pyarrow as pa

    from psdfactory.io import table_from_columns, write_parquet

    rng = np.random.default_rng(5)
    for n in (0, 1, 7, 8, 9, 203):
        xyz = rng.normal(size=(n, 3))
        cols = {
            "scene_id": np.full(n, "train-000005"),
            "name": np.array([("grès é" * (i % 3)) for i in range(n)], dtype=str),
            "i32": np.arange(n, dtype=np.int32),
            "i64": rng.integers(-5, 5, size=n),
            "u16": np.arange(n, dtype=np.uint16),
            "f32": rng.normal(size=n).astype(np.float32),
            "x": xyz[:, 0],  # a strided view
            "reversed": xyz[::-1, 2],
            "big_endian": xyz[:, 1].astype(">f8"),
            "settled": rng.random(n) > 0.5,
            "listed": list(range(n)),  # not an array: pa.array's own way
        }
        got = table_from_columns(cols)
        want = pa.table({k: (v.astype("<f8") if k == "big_endian" else v) for k, v in cols.items()})
        assert got.schema == want.schema, n
        assert got.equals(want), n
        write_parquet(tmp_path / "got.parquet", got)
        write_parquet(tmp_path / "want.parquet", want)
        assert (tmp_path / "got.parquet").read_bytes() == (tmp_path / "want.parquet").read_bytes(), n
    assert table_from_columns({"s": np.full(0, "abc")}).schema.field("s").type == pa.string()
    masked = np.ma.masked_array([1, 2, 3], mask=[0, 1, 0])  # its mask becomes a null, as pa.table has it
    assert table_from_columns({"m": masked}).column("m").to_pylist() == [1, None, 3]
