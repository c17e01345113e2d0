"""predict refuses, before any work and in one line, an output that would overwrite or mix with
an input (an image, an input folder, the model, another output), and arguments that make no
sense; every input and the model are byte-identical afterwards. The checks come before the
model is loaded, so a stand-in model file serves."""

import os
from pathlib import Path

import pytest

from psdfactory.cli import main


@pytest.fixture
def scene(tmp_path):
    d = tmp_path / "photos"
    d.mkdir()
    (d / "a.png").write_bytes(b"\x89PNG not really")
    (d / "b.jpg").write_bytes(b"\xff\xd8 not really")
    model = tmp_path / "model.pt"
    model.write_bytes(b"weights" * 100)
    return tmp_path, d, model


def snapshot(root):
    return {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}


def refused(capsys, args, *expect):
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("psdfactory predict: error:"), err
    for e in expect:
        assert e in err[0], (e, err[0])


@pytest.mark.parametrize("case", ["masks_here", "overlay_twice", "out_is_image", "out_is_model", "out_in_folder",
                                  "particles_is_out", "masks_in_input_folder", "out_is_folder", "masks_is_file",
                                  "json_beside_onnx", "out_below_a_file", "masks_below_a_file"])
def test_an_output_that_is_an_input_or_another_output_is_refused(scene, capsys, monkeypatch, case):
    root, photos, model = scene
    a, b = str(photos / "a.png"), str(photos / "b.jpg")
    m = ["predict", "--model", str(model)]
    onnx = root / "model.onnx"
    onnx.write_bytes(b"onnx")
    (root / "meta.json").write_text("{}")
    (root / "somefile").write_text("x")
    cases = {
        "masks_here": ([*m, "--masks", str(photos), a, b], "--masks", "holds the input image"),
        "overlay_twice": ([*m, "--overlay", str(root / "o"), "--masks", str(root / "o"), a], "write over each other"),
        "out_is_image": ([*m, "--out", a, a, b], "--out", "must end in .csv or .json"),
        "out_is_model": (["predict", "--model", str(root / "p.csv"), "--out", str(root / "p.csv"), a], "is the model"),
        "out_in_folder": ([*m, "--out", str(photos / "p.csv"), str(photos)], "among the input images"),
        "particles_is_out": ([*m, "--out", str(root / "x.csv"), "--particles", str(root / "x.csv"), a],
                             "write over each other"),
        "masks_in_input_folder": ([*m, "--masks", str(photos / "masks"), str(photos)], "inside the input folder"),
        "out_is_folder": ([*m, "--out", str(root / "d.csv"), a], "is a folder"),
        "masks_is_file": ([*m, "--masks", str(root / "somefile"), a], "is a file"),
        "json_beside_onnx": (["predict", "--model", str(onnx), "--out", str(root / "meta.json"), a], "is the model"),
        "out_below_a_file": ([*m, "--out", str(root / "somefile" / "p.csv"), a], "somefile is a file, not a folder"),
        "masks_below_a_file": ([*m, "--masks", str(root / "somefile" / "m"), a], "is a file, not a folder"),
    }
    (root / "d.csv").mkdir()
    args, *expect = cases[case]
    before = snapshot(root)
    refused(capsys, args, *expect)
    assert snapshot(root) == before and not (root / "o").exists() and not (photos / "masks").exists()


def test_a_log_over_the_model_or_an_image_is_refused_before_it_is_opened(scene, capsys):
    root, photos, model = scene
    before = snapshot(root)
    for log in (model, photos / "a.png"):
        assert main(["--log", str(log), "predict", "--model", str(model), str(photos / "a.png")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--log" in err[0] and "give the log its own file" in err[0]
    assert snapshot(root) == before


@pytest.mark.parametrize("value", ["0", "-1", "1e-300", "nan", "inf", "5000", "abc"])
def test_mm_per_px_must_be_a_finite_scale(scene, capsys, value):
    root, photos, model = scene
    with pytest.raises(SystemExit) as e:
        main(["predict", "--model", str(model), "--mm-per-px", value, str(photos)])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--mm-per-px" in err and "mm per pixel from 0.0001 to 1000" in err


@pytest.mark.parametrize("device,says", [("nonsense", "not one PyTorch knows"), ("cuda:7", "CUDA"),
                                         ("xla", "runs on cpu, cuda or mps")])
def test_a_device_this_machine_lacks_is_one_line(scene, capsys, device, says):
    import torch

    if device.startswith("cuda") and torch.cuda.device_count() > 7:
        pytest.skip("this machine has that device")
    root, photos, model = scene
    before = snapshot(root)
    refused(capsys, ["predict", "--model", str(model), "--device", device, str(photos)], "device", says)
    assert snapshot(root) == before


def test_two_runs_on_one_out_the_second_is_refused_and_the_lock_dies_with_its_holder(scene, capsys, tmp_path):
    import signal
    import subprocess
    import sys
    import time

    from psdfactory.deploy.predict import OutLock, lock_path

    root, photos, model = scene
    out = root / "same.csv"
    code = ("import sys, time; from pathlib import Path; from psdfactory.deploy.predict import OutLock; "
            "OutLock(Path(sys.argv[1])); print('held', flush=True); time.sleep(60)")
    holder = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        before = snapshot(photos)
        refused(capsys, ["predict", "--model", str(model), "--out", str(out), str(photos)],
                f"--out {out}: another predict (pid {holder.pid}) is writing it now")
        assert capsys.readouterr().out == ""  # nothing printed before the error (no table header)
        assert snapshot(photos) == before and not out.exists()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    time.sleep(0.1)
    lock = OutLock(out)  # kill -9 released it
    lock.release()
    assert not lock_path(out).exists()


@pytest.mark.parametrize("args,says", [
    (["show", "-n", "0"], "give a whole number of at least 1"),
    (["show", "-n", "many"], "give a whole number of at least 1"),
])
def test_counts_must_be_positive(capsys, args, says):
    with pytest.raises(SystemExit) as e:
        main(args)
    assert e.value.code == 2 and says in capsys.readouterr().err


def test_show_and_report_refuse_bad_files_in_one_line(tmp_path, capsys):
    (tmp_path / "folder").mkdir()
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "list.json").write_text("[1, 2]")
    common = ["--metrics", "m.json", "--scatters", "s.png", "--histories", "h.csv", "--bench", "b.json",
              "--manifests", "x.parquet", "--html", str(tmp_path / "r.html"), "--md", str(tmp_path / "r.md")]
    for args, says in [
        (["show", "--out", str(tmp_path / "folder")], "is a folder"),
        (["show", "--out", str(tmp_path / "sheet.jpg")], "must end in .png"),
        (["report", "--config-json", str(tmp_path / "missing.json"), *common], "missing file"),
        (["report", "--config-json", str(tmp_path / "bad.json"), *common], "is not valid JSON"),
        (["report", "--config-json", str(tmp_path / "list.json"), *common], "must hold a JSON object"),
    ]:
        assert main(args) == 2, args
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0] and "Traceback" not in err[0], (args, err)


def test_what_is_not_an_image_file_is_named_for_what_it_is(tmp_path):
    from psdfactory import PsdError
    from psdfactory.io import read_photo

    os.mkfifo(tmp_path / "fifo.png")
    (tmp_path / "loop.png").symlink_to(tmp_path / "loop.png")
    (tmp_path / "dangling.png").symlink_to(tmp_path / "nowhere.png")
    (tmp_path / "folder.png").mkdir()
    cases = {"fifo.png": "a FIFO (named pipe), not an image file", "loop.png": "a loop of symbolic links",
             "dangling.png": "a symbolic link to nothing", "folder.png": "a folder, not an image file",
             "nothing.png": "missing image", "x" * 300 + ".png": "file name is too long",
             "/dev/null": "a device, not an image file"}
    for name, says in cases.items():
        with pytest.raises(PsdError) as e:
            read_photo(tmp_path / name)
        assert says in str(e.value), (name, str(e.value))


def test_a_folder_without_images_names_itself_and_what_was_looked_for(scene, capsys):
    root, photos, model = scene
    empty = root / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("x")
    from psdfactory import PsdError
    from psdfactory.deploy.predict import expand_inputs, image_files

    assert expand_inputs(["y" * 300 + ".png"]) == [Path("y" * 300 + ".png")]  # its row will say why
    with pytest.raises(PsdError) as e:
        image_files([str(empty)])
    assert f"no image files in {empty} (looked for .bmp, .jpeg, .jpg, .png" in str(e.value)


def test_a_truncated_or_overwritten_model_is_not_called_dangerous(tmp_path):
    import torch

    from psdfactory import PsdError
    from psdfactory.learn.runtime import load_checkpoint

    good = tmp_path / "good.pt"
    torch.save({"meta": {}, "state_dict": {"w": torch.zeros(4000)}}, good)
    data = good.read_bytes()
    (tmp_path / "truncated.pt").write_bytes(data[: len(data) // 2])
    (tmp_path / "log.pt").write_text("2026-11-25 09:00:00 INFO psdfactory: a log line\n" * 8)
    (tmp_path / "empty.pt").write_bytes(b"")
    for name in ("truncated.pt", "log.pt", "empty.pt"):
        with pytest.raises(PsdError) as e:
            load_checkpoint(tmp_path / name)
        msg = str(e.value)
        assert "not a file torch.save wrote" in msg and "could run code" not in msg, (name, msg)
    assert load_checkpoint(good)["meta"] == {}


def test_an_empty_or_text_onnx_is_one_line(tmp_path, capsys):
    pytest.importorskip("onnxruntime")
    import json

    from PIL import Image

    meta = {"arch": "resnet18", "input_size": 32, "image_resolution": 32, "mm_per_px": 0.5,
            "target_stats": {k: [1.0, 2.0, 3.0] for k in ("mean", "std", "part_mean", "part_std")}}
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    Image.new("RGB", (32, 32)).save(tmp_path / "a.png")
    for content, says in ((b"", "is empty (0 bytes)"), (b"not a model\n", "not an ONNX model ONNX Runtime can load")):
        (tmp_path / "model.onnx").write_bytes(content)
        assert main(["predict", "--model", str(tmp_path / "model.onnx"), str(tmp_path / "a.png")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0] and "Traceback" not in err[0], err


def test_report_and_show_never_write_over_what_they_read(tmp_path, capsys):
    (tmp_path / "m.json").write_text("{}")
    common = ["--metrics", str(tmp_path / "m.json"), "--scatters", "s.png", "--histories", "h.csv",
              "--bench", "b.json", "--manifests", "x.parquet"]
    before = (tmp_path / "m.json").read_bytes()
    for args, says in [
        (["report", *common, "--html", str(tmp_path / "m.json"), "--md", str(tmp_path / "r.md")], "must end in .html"),
        (["report", *common, "--html", str(tmp_path / "x.html"), "--md", str(tmp_path / "x.md"),
          "--ceilings", str(tmp_path / "x.html")], "is also an input of the report"),
        (["show", "--results", str(tmp_path), "--dataset", "d", "--out", str(tmp_path / "d" / "scenes" / "s.png")],
         "inside the scenes it shows"),
    ]:
        assert main(args) == 2, args
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0], (args, err)
    assert (tmp_path / "m.json").read_bytes() == before


def test_log_check_takes_lists_of_paths(tmp_path, capsys):
    """Commands whose flags take several files (ceiling's --scenes/--particles) get the same --log
    check: a log over one of them is refused, a log of its own runs the command."""
    shard = tmp_path / "shard.parquet"
    shard.write_bytes(b"PAR1")
    args = ["ceiling", "--params", "{}", "--dataset", "d", "--scenes", str(shard), "--particles", str(shard),
            "--results", str(tmp_path), "--out", str(tmp_path / "c.json")]
    assert main(["--log", str(shard), *args]) == 2
    assert "give the log its own file" in capsys.readouterr().err and shard.read_bytes() == b"PAR1"
    code = main(["--log", str(tmp_path / "ceiling.log"), *args])  # runs (and fails on the stand-in shard)
    assert code in (1, 2) and (tmp_path / "ceiling.log").is_file()
