"""Packs: a dataset's scenes as WebDataset tar shards (`psdfactory pack`) and ShardScenes, the
training-side reader that deals shards to DDP ranks and loader workers."""

import json
import tarfile
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from psdfactory import PsdError
from psdfactory.io import read_png
from psdfactory.packs import PackSpec, epoch_order, left_out, read_index, shard_plan, shard_sizes
from psdfactory.psd import TARGETS

from .conftest import split_dataset, tiny_config

SPLITS = ["train"] * 6 + ["val"] * 2


def _relabel(table: pa.Table, column: str, values) -> pa.Table:
    return table.set_column(table.schema.get_field_index(column), column, pa.array(values))


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> Path:
    """8 tiny scenes at 32 px (6 train, 2 val) as dataset `tiny`, and the same scenes' manifest
    again as dataset `twin` (other scene ids, the same images): two datasets to pack together."""
    root = tmp_path_factory.mktemp("res")
    split_dataset(root, SPLITS)
    m = root / "tiny" / "manifest"
    t = pq.read_table(m / "scenes" / "shard-00000.parquet")
    twin = root / "twin" / "manifest"
    (twin / "scenes").mkdir(parents=True)
    (twin / "particles").mkdir(parents=True)
    ids = [s.replace("tiny", "twin") for s in t.column("scene_id").to_pylist()]
    pq.write_table(_relabel(_relabel(t, "scene_id", ids), "dataset", ["twin"] * len(ids)),
                   twin / "scenes" / "shard-00000.parquet")
    p = pq.read_table(m / "particles" / "shard-00000.parquet")
    pq.write_table(_relabel(p, "scene_id", [s.replace("tiny", "twin") for s in p.column("scene_id").to_pylist()]),
                   twin / "particles" / "shard-00000.parquet")
    return root


@pytest.fixture(scope="module")
def packed(results, tmp_path_factory) -> Path:
    """`tiny` packed losslessly at its own size, one scene a shard."""
    from psdfactory.learn.shards import pack

    out = tmp_path_factory.mktemp("packs") / "png"
    pack(results, ["tiny"], out, PackSpec(size=32, image_format="png", shard_scenes=1))
    return out


def test_shard_sizes_are_as_few_as_allowed_and_within_one_of_each_other():
    assert shard_sizes(10, 4) == [4, 3, 3]
    assert shard_sizes(8, 4) == [4, 4]
    assert shard_sizes(3, 10) == [3]
    assert shard_sizes(0, 5) == []
    for n, most in [(1001, 250), (7, 1), (99, 10)]:
        s = shard_sizes(n, most)
        assert sum(s) == n and max(s) <= most and max(s) - min(s) <= 1 and len(s) == -(-n // most)


def test_shard_plan_deals_shards_without_overlap_and_the_same_count_to_every_rank():
    counts = [3, 3, 3, 2]
    # two ranks, one worker each: rank 0 reads shards 0 and 2, rank 1 shards 1 and 3: two shards of at least 2
    # scenes each, whatever their order, so both yield 4
    assert shard_plan(counts, 0, 2, 0, 1) == ([0, 2], 4)
    assert shard_plan(counts, 1, 2, 0, 1) == ([1, 3], 4)
    assert shard_plan([3, 3, 3], 1, 2, 0, 1) == ([1], 3)  # rank 0 has two shards, rank 1 one
    assert left_out([3, 3, 3], 2, 1) == 3 and left_out([3, 3, 3, 2], 2, 1) == 3
    assert shard_plan(counts, 0, 1, 0, 1) == ([0, 1, 2, 3], 11)  # one rank: every scene
    assert shard_plan(counts, 0, 1, 1, 2) == ([1, 3], 5) and left_out(counts, 1, 2) == 0
    counts = [5, 5, 4, 4, 4, 4, 4, 4]
    for world, workers in [(1, 1), (2, 2), (4, 2), (1, 8)]:
        seen, per_rank = [], []
        for r in range(world):
            total = 0
            for w in range(workers):
                mine, n = shard_plan(counts, r, world, w, workers)
                assert n <= sum(counts[i] for i in mine)
                seen += mine
                total += n
            per_rank.append(total)
        assert sorted(seen) == list(range(len(counts)))  # every shard read once
        assert len(set(per_rank)) == 1  # every rank the same number of samples


def test_the_epoch_order_is_the_same_everywhere_and_another_each_epoch():
    shards = [{"name": f"s{i}"} for i in range(20)]
    assert epoch_order(shards, 3, 0) == epoch_order(shards, 3, 0)
    assert epoch_order(shards, 3, 0) != epoch_order(shards, 3, 1)
    assert sorted(s["name"] for s in epoch_order(shards, 3, 5)) == sorted(s["name"] for s in shards)


def test_a_lossless_pack_holds_each_scene_as_the_factory_wrote_it(results, packed):
    from psdfactory.learn.shards import ShardScenes

    index = read_index(packed)
    assert index["splits"]["train"]["scenes"] == 6 and index["splits"]["val"]["scenes"] == 2
    assert len(index["splits"]["train"]["shards"]) == 6 and index["size_definition"] and index["weighting"]
    rows = {r["scene_id"]: r for r in pq.read_table(results / "tiny" / "manifest" / "scenes").to_pylist()}
    parts = pq.read_table(results / "tiny" / "manifest" / "particles").to_pandas()
    got = list(ShardScenes(packed, "train", fields=("image", "targets", "mask", "particles", "meta"), seed=1))
    assert sorted(m["scene_id"] for *_, m in got) == sorted(k for k, r in rows.items() if r["split"] == "train")
    for image, y, mask, particles, meta in got:
        row = rows[meta["scene_id"]]
        assert image.dtype == torch.uint8 and image.shape == (3, 32, 32)
        assert np.array_equal(image.permute(1, 2, 0).numpy(), read_png(results / row["image_path"]))
        assert np.array_equal(mask.numpy(), read_png(results / row["mask_path"]).astype(np.int32))
        assert torch.allclose(y, torch.tensor([row[t] for t in TARGETS], dtype=torch.float32))
        mine = parts[parts.scene_id == meta["scene_id"]].sort_values("particle_id")
        assert np.allclose(particles[np.argsort(particles[:, 0])][:, :2], mine[["particle_id", "size_mm"]].to_numpy())
        assert meta["packed_mm_per_px"] == pytest.approx(row["mm_per_px"])  # packed at its own size
        assert "image_path" not in meta


def test_a_jpeg_pack_at_another_size_holds_what_training_would_read(results, tmp_path):
    from psdfactory.learn.data import to_input
    from psdfactory.learn.shards import ShardScenes, pack

    pack(results, ["tiny"], tmp_path / "p", PackSpec(size=48, shard_scenes=4), splits=("val",))
    rows = {r["scene_id"]: r for r in pq.read_table(results / "tiny" / "manifest" / "scenes").to_pylist()}
    index = read_index(tmp_path / "p")
    assert list(index["splits"]) == ["val"]
    for image, mask, meta in ShardScenes(tmp_path / "p", "val", fields=("image", "mask", "meta")):
        row = rows[meta["scene_id"]]
        want = to_input(read_png(results / row["image_path"]), 48)
        assert image.shape == want.shape == (3, 48, 48)
        assert (image.float() - want.float()).abs().mean() < 4  # JPEG q95
        assert mask.shape == (48, 48) and set(np.unique(mask.numpy())) <= set(np.unique(read_png(
            results / row["mask_path"])))  # nearest neighbour: ids stay ids
        assert meta["packed_mm_per_px"] == pytest.approx(row["mm_per_px"] * 32 / 48)


def test_two_datasets_are_packed_together_mixed_and_the_same_twice(results, tmp_path):
    from psdfactory.learn.shards import pack

    spec = PackSpec(size=32, shard_scenes=4, masks=False, seed=5)
    a = pack(results, ["tiny", "twin"], tmp_path / "a", spec)
    b = pack(results, ["tiny", "twin"], tmp_path / "b", spec, jobs=2)  # encoded in two worker processes
    assert a["splits"] == b["splits"]  # byte for byte: the SHA-256 of every shard
    assert a["splits"]["train"]["scenes"] == 12 and [s["scenes"] for s in a["splits"]["train"]["shards"]] == [4, 4, 4]
    with tarfile.open(tmp_path / "a" / "train-000000.tar") as tar:
        names = tar.getnames()
    assert not any(n.endswith((".mask.png", ".npy")) for n in names)
    first = {n.split("-")[0] for n in names}
    c = pack(results, ["tiny", "twin"], tmp_path / "c", PackSpec(size=32, shard_scenes=4, masks=False, seed=6))
    assert c["splits"]["train"]["shards"] != a["splits"]["train"]["shards"]  # another seed, another order
    assert first <= {"tiny", "twin"}


def test_any_webdataset_reader_takes_a_pack(packed):
    import webdataset as wds

    urls = [str(packed / s["name"]) for s in read_index(packed)["splits"]["val"]["shards"]]
    samples = list(wds.WebDataset(urls, shardshuffle=False, empty_check=False))
    assert sorted(s["__key__"] for s in samples) == ["tiny-000006", "tiny-000007"]
    assert json.loads(samples[0]["json"])["split"] == "val"


def test_shards_are_read_through_a_url_as_from_object_storage(packed):
    """url="pipe:..." as for `aws s3 cp s3://.../{name} -`: here `cat` stands in for the copy."""
    from psdfactory.learn.shards import ShardScenes

    local = sorted(m["scene_id"] for (m,) in ShardScenes(packed, "train", fields=("meta",)))
    piped = ShardScenes(packed, "train", fields=("meta",), url=f"pipe:cat {packed}/{{name}}")
    assert sorted(m["scene_id"] for (m,) in piped) == local and len(local) == 6


def test_ranks_and_loader_workers_read_each_scene_once_and_every_rank_as_many(packed):
    from psdfactory.learn.shards import ShardScenes

    for epoch in (0, 1):
        per_rank = []
        for rank in range(2):
            ds = ShardScenes(packed, "train", fields=("meta",), num_workers=2, world=(rank, 2), seed=4)
            ds.set_epoch(epoch)
            loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=2)
            ids = [m["scene_id"] for (m,) in loader]
            assert len(ids) == len(ds) == 3 and len(set(ids)) == 3
            per_rank.append(ids)
        assert not set(per_rank[0]) & set(per_rank[1])
    # the same seed and epoch: the same order; another epoch: the shards dealt otherwise
    one = [m["scene_id"] for (m,) in ShardScenes(packed, "train", fields=("meta",), seed=4)]
    again = [m["scene_id"] for (m,) in ShardScenes(packed, "train", fields=("meta",), seed=4)]
    other = ShardScenes(packed, "train", fields=("meta",), seed=4)
    other.set_epoch(1)
    assert one == again and one != [m["scene_id"] for (m,) in other]


def test_the_rank_comes_from_the_environment_torchrun_sets(packed, monkeypatch):
    from psdfactory.learn.shards import ShardScenes

    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "3")
    ds = ShardScenes(packed, "train", fields=("meta",))
    assert len(ds) == 2 and len(list(ds)) == 2


def test_what_a_pack_cannot_serve_is_refused_with_the_reason(packed, tmp_path):
    from psdfactory.learn.shards import ShardScenes

    with pytest.raises(PsdError, match="2 val shards for 2 ranks x 2 loader workers"):
        ShardScenes(packed, "val", num_workers=2, world=(0, 2))
    with pytest.raises(PsdError, match="no 'test' scenes"):
        ShardScenes(packed, "test")
    with pytest.raises(PsdError, match="choose from"):
        ShardScenes(packed, "train", fields=("pixels",))
    ds = ShardScenes(packed, "train", num_workers=0)
    with pytest.raises(PsdError, match="give the DataLoader's num_workers"):
        next(iter(torch.utils.data.DataLoader(ds, batch_size=None, num_workers=2)))
    with pytest.raises(PsdError, match="index.json is missing"):
        ShardScenes(tmp_path, "train")


def test_a_truncated_shard_is_named(packed, tmp_path):
    import shutil

    from psdfactory.learn.shards import ShardScenes

    copy = tmp_path / "copy"
    shutil.copytree(packed, copy)
    shard = read_index(copy)["splits"]["train"]["shards"][0]["name"]
    data = (copy / shard).read_bytes()
    (copy / shard).write_bytes(data[: len(data) // 2])
    with pytest.raises(PsdError, match=f"{shard} is {len(data) // 2} bytes, the pack's index says {len(data)}"):
        list(ShardScenes(copy, "train"))
    # read through a URL (no size check before reading): the damage is named as it is met
    with pytest.raises(PsdError, match=f"{shard}: (not a readable shard|scene tiny-\\d+ has no)"):
        list(ShardScenes(copy, "train", url=str(copy) + "/{name}", shuffle_buffer=1))


def test_an_interrupted_pack_leaves_the_old_pack_as_it_was(results, packed, tmp_path, monkeypatch):
    import shutil

    from psdfactory.learn import shards

    out = tmp_path / "p"
    shutil.copytree(packed, out)
    before = (out / "index.json").read_text()
    calls = []

    def failing(*args):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return shards.scene_sample(*args)

    monkeypatch.setattr(shards, "_sample_job", lambda a: failing(*a))
    with pytest.raises(KeyboardInterrupt):
        shards.pack(results, ["tiny"], out, PackSpec(size=48, shard_scenes=2))
    assert (out / "index.json").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p"]  # no half pack beside it


def test_a_pack_carries_the_users_umask(results, tmp_path):
    import os
    import stat

    from psdfactory.learn.shards import pack

    old = os.umask(0o002)
    try:
        pack(results, ["tiny"], tmp_path / "p", PackSpec(size=32, shard_scenes=4, masks=False))
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "p").stat().st_mode) == 0o775
    for f in (tmp_path / "p").iterdir():
        assert stat.S_IMODE(f.stat().st_mode) == 0o664, f.name


def test_pack_refuses_what_would_make_a_wrong_pack(results, tmp_path):
    from psdfactory.learn.shards import pack

    for out in (results / "tiny" / "pack", results, results.parent):
        with pytest.raises(PsdError, match="overlaps .*which the pack reads"):
            pack(results, ["tiny"], out, PackSpec())
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    with pytest.raises(PsdError, match="holds files and is not a pack"):
        pack(results, ["tiny"], tmp_path / "mine", PackSpec())
    assert (tmp_path / "mine" / "notes.txt").read_text() == "mine"
    with pytest.raises(PsdError, match="--size 8"):
        pack(results, ["tiny"], tmp_path / "p", PackSpec(size=8))
    with pytest.raises(PsdError, match=r"no scenes in the split test to pack \(the manifests have: train, val\)"):
        pack(results, ["tiny"], tmp_path / "p", PackSpec(), splits=("train", "test"))
    with pytest.raises(PsdError, match="no manifest"):
        pack(results, ["missing"], tmp_path / "p", PackSpec())
    assert not (tmp_path / "p").exists()


def test_the_batches_an_epoch_count_each_loader_workers_last_batch(packed):
    from psdfactory.learn.shards import ShardScenes

    ds = ShardScenes(packed, "train", num_workers=2)  # 6 shards of one scene: 3 a worker, batches of 2, 1
    loader = torch.utils.data.DataLoader(ds, batch_size=2, num_workers=2)
    assert ds.batches(2) == 4 == sum(1 for _ in loader) and len(loader) == 3  # what DataLoader would count


def test_the_pack_command(results, tmp_path, capsys):
    from psdfactory.cli import main

    assert main(["pack", "--results", str(results), "--datasets", "tiny", "--size", "32", "--shard-scenes", "3",
                 "--no-masks", "--out", str(tmp_path / "p")]) in (0, None)
    index = read_index(tmp_path / "p")
    assert [s["scenes"] for s in index["splits"]["train"]["shards"]] == [3, 3] and not index["masks"]
    assert main(["pack", "--results", str(results), "--datasets", "tiny", "--quality", "101",
                 "--out", str(tmp_path / "q")]) == 2
    assert "--quality" in capsys.readouterr().err
    # --verify: every shard against the index; a damaged one is named, and the exit status says so
    assert main(["pack", "--verify", str(tmp_path / "p")]) == 0
    assert "3 of 3 shards as the index says" in capsys.readouterr().out  # 2 train shards, 1 val
    shard = tmp_path / "p" / index["splits"]["train"]["shards"][1]["name"]
    data = bytearray(shard.read_bytes())
    data[700] ^= 0xFF  # one byte changed, the size the same
    shard.write_bytes(bytes(data))
    assert main(["pack", "--verify", str(tmp_path / "p")]) == 1
    out = capsys.readouterr().out
    assert f"{shard}: " in out and "damaged or incomplete" in out and "2 of 3 shards as the index says" in out


def test_a_pack_holds_the_size_codes_training_makes_from_the_scene_folders(results, packed):
    from psdfactory.learn.data import SceneImages, manifest_rows, particles_by_scene
    from psdfactory.learn.shards import ShardScenes
    from psdfactory.learn.size_cells import ScenesWithSizeCodes

    rows = manifest_rows(results, "tiny", ("train",))
    folders = ScenesWithSizeCodes(SceneImages(results, rows, 32), particles_by_scene(results, ["tiny"]))
    want = {r["scene_id"]: folders.codes(i) for i, r in enumerate(rows)}
    got = list(ShardScenes(packed, "train", fields=("codes", "meta")))
    assert len(got) == len(want)
    for codes, meta in got:
        assert codes.dtype == torch.uint8 and torch.equal(codes, want[meta["scene_id"]])


def train_slice(**over) -> dict:
    from psdfactory import config as psd_config

    p = psd_config.train_params(tiny_config(), "resnet18")
    p.update(pretrained="none", epochs=2, batch_size=3, lr=3e-3, input_size=32, precision="fp32", seed=1,
             early_stopping_patience=50, datasets=["tiny"], size_cells=1.0)
    p.update(over)
    return p


@pytest.fixture(scope="module")
def pack32(results, tmp_path_factory) -> Path:
    """`tiny` at 32 px JPEG with masks, shards of at most 3 scenes: 2 train shards, 1 val."""
    from psdfactory.learn.shards import pack

    out = tmp_path_factory.mktemp("packs") / "p32"
    pack(results, ["tiny"], out, PackSpec(size=32, shard_scenes=3))
    return out


def test_a_cnn_trains_from_a_pack_as_from_the_folders(results, pack32, tmp_path):
    from psdfactory.learn.runtime import load_model
    from psdfactory.learn.train import train_from_params

    folders = train_from_params(train_slice(), results, tmp_path / "folders")
    packed = train_from_params(train_slice(), results, tmp_path / "pack", pack=pack32, loader_workers=2)
    for k in ("size_definition", "weighting", "mm_per_px", "image_resolution", "input_size"):
        assert packed[k] == pytest.approx(folders[k]), k
    for k, v in folders["target_stats"].items():
        assert packed["target_stats"][k] == pytest.approx(v), k
    assert packed["pack"] == {"path": str(pack32), "datasets": ["tiny"], "ranks": 1}
    assert packed["epochs_run"] == 2 and (tmp_path / "pack" / "history.csv").is_file()
    model, meta = load_model(tmp_path / "pack" / "model.pt")
    assert meta["pack"]["ranks"] == 1
    assert model(torch.zeros(1, 3, 32, 32)).shape[-1] == 3


def test_what_cannot_train_from_a_pack_is_refused(results, pack32, tmp_path, monkeypatch):
    from psdfactory.learn.train import train_from_params

    with pytest.raises(PsdError, match="holds 32 px images, resnet18 trains at 64 px: pack with --size 64"):
        train_from_params(train_slice(input_size=64), results, tmp_path, pack=pack32)
    with pytest.raises(PsdError, match="'instances' does not train from a pack"):
        from psdfactory import config as psd_config

        train_from_params(psd_config.train_params(tiny_config(), "instances"), results, tmp_path, pack=pack32)
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    with pytest.raises(PsdError, match="training on 2 processes reads a pack"):
        train_from_params(train_slice(), results, tmp_path)


@pytest.mark.slow
def test_two_processes_train_one_model_from_a_pack_under_torchrun(results, pack32, tmp_path):
    """torchrun, 2 CPU processes (Gloo): each rank reads its own train shard, gradients are averaged,
    rank 0 alone writes the model, the history and the log lines."""
    import subprocess
    import sys

    out = tmp_path / "ddp"
    torchrun = Path(sys.executable).with_name("torchrun")
    cmd = [str(torchrun), "--standalone", "--nproc-per-node", "2", "-m", "psdfactory.cli", "train",
           "--params", json.dumps(train_slice()), "--results", str(results), "--out-dir", str(out),
           "--pack", str(pack32), "--threads", "1"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    meta = torch.load(out / "model.pt", weights_only=False)["meta"]
    assert meta["pack"]["ranks"] == 2 and meta["epochs_run"] == 2
    assert "distributed training: 2 processes (gloo)" in run.stderr
    assert run.stderr.count("epoch 1: train loss") == 1  # rank 0's line only
    assert len((out / "history.csv").read_text().splitlines()) == 3
