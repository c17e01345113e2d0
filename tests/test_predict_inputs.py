"""`psdfactory predict` on hostile and odd images, and on a folder of many: one reader
(io.read_photo) that refuses bombs from the header, names every bad file with its reason,
streams rows to --out as they come and resumes an interrupted run."""

from __future__ import annotations

import builtins
import csv
import io
import json
import os
import signal
import struct
import subprocess
import sys
import textwrap
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from psdfactory import PsdError
from psdfactory.io import open_image, read_photo, reduce_factor

META = {"arch": "resnet18", "input_size": 32, "image_resolution": 32, "mm_per_px": 0.5,
        "target_stats": {"mean": [1.0, 2.0, 3.0], "std": [0.5, 0.5, 0.5], "part_mean": [1.0, 1.0, 1.0],
                         "part_std": [0.2, 0.2, 0.2]}}


def png_bytes(w: int, h: int, rows: int = 1, bit_depth: int = 8, colour_type: int = 0) -> bytes:
    """A PNG whose header says w x h, with only `rows` rows of (zero) pixel data."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, bit_depth, colour_type, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * (w + 1) * rows))
            + chunk(b"IEND", b""))


def save(img: Image.Image, path: Path, **kw) -> Path:
    img.save(path, **kw)
    return path


def two_halves(w: int, h: int, left=(255, 0, 0), right=(0, 0, 255)) -> Image.Image:
    a = np.zeros((h, w, 3), np.uint8)
    a[:, : w // 2] = left
    a[:, w // 2 :] = right
    return Image.fromarray(a)


@pytest.fixture()
def folder(tmp_path):
    """One file of each kind, good and bad."""
    d = tmp_path / "imgs"
    d.mkdir()
    save(two_halves(40, 30), d / "good.png")
    save(Image.fromarray(np.full((20, 24), 128, np.uint8)), d / "grey.png")
    save(Image.fromarray((np.arange(20 * 24).reshape(20, 24) * 100).astype(np.uint16)), d / "grey16.png")
    save(Image.new("RGBA", (24, 20), (10, 200, 30, 0)), d / "rgba.png")
    pal = Image.new("P", (24, 20))
    pal.putpalette([0, 0, 0, 250, 120, 5] + [0] * 762)
    pal.paste(1, (0, 0, 24, 20))
    save(pal, d / "palette.png")
    save(Image.new("1", (24, 20), 1), d / "bilevel.png")
    save(Image.new("CMYK", (24, 20), (0, 255, 255, 0)), d / "cmyk.jpg", quality=95)
    exif = Image.Exif()
    exif[0x0112] = 6  # shown rotated 90° clockwise
    save(two_halves(40, 20), d / "exif6.jpg", exif=exif.tobytes(), quality=95)
    (d / "bomb.png").write_bytes(png_bytes(30000, 30000))
    good = (d / "good.png").read_bytes()
    (d / "truncated.png").write_bytes(good[: len(good) // 2])
    buf = io.BytesIO()
    two_halves(64, 48).save(buf, format="JPEG")
    (d / "truncated.jpg").write_bytes(buf.getvalue()[: len(buf.getvalue()) // 2])
    (d / "zero.png").write_bytes(b"")
    (d / "notes.jpg").write_text("these are not pixels\n")
    save(two_halves(40, 30), d / "locked.png")
    return d


BAD = {  # file → what its error must say
    "bomb.png": "refused: its header declares 900,000,000 pixels, more than the limit of 89,478,485 (a decompression",
    "truncated.png": "not a readable image",
    "truncated.jpg": "truncated",
    "zero.png": "an empty file (0 bytes)",
    "notes.jpg": "not an image format PIL can read",
    "locked.png": "permission denied",
}


@pytest.fixture()
def locked(folder, monkeypatch):
    """locked.png cannot be opened: chmod 000, or (as root, who may read anything) an open()
    that refuses it as the kernel would."""
    target = folder / "locked.png"
    if os.geteuid() != 0:
        target.chmod(0)
        yield target
        target.chmod(0o644)
        return
    real = builtins.open

    def guarded(file, *a, **k):
        if isinstance(file, (str, os.PathLike)) and os.path.abspath(file) == str(target):
            raise PermissionError(13, "Permission denied", str(file))
        return real(file, *a, **k)

    monkeypatch.setattr(builtins, "open", guarded)
    yield target


def test_every_kind_of_image_is_read_upright_as_rgb8(folder):
    img, hw = read_photo(folder / "good.png")
    assert img.shape == (30, 40, 3) and img.dtype == np.uint8 and hw == (30, 40)
    assert (img[0, 0] == (255, 0, 0)).all() and (img[0, -1] == (0, 0, 255)).all()
    grey, _ = read_photo(folder / "grey.png")
    assert grey.shape == (20, 24, 3) and (grey == 128).all()
    g16, _ = read_photo(folder / "grey16.png")  # 16-bit: scaled to 8 bits, not clipped to white
    ramp = (np.arange(20 * 24).reshape(20, 24) * 100).astype(np.float64)
    assert g16.shape == (20, 24, 3) and np.abs(g16[:, :, 0] - ramp / 257).max() <= 0.5 + 1e-9
    rgba, _ = read_photo(folder / "rgba.png")
    assert (rgba == (10, 200, 30)).all()  # alpha dropped, colour kept
    pal, _ = read_photo(folder / "palette.png")
    assert (pal == (250, 120, 5)).all()
    bilevel, _ = read_photo(folder / "bilevel.png")
    assert (bilevel == 255).all()
    cmyk, _ = read_photo(folder / "cmyk.jpg")
    assert cmyk.shape == (20, 24, 3) and np.abs(cmyk.astype(int) - (255, 0, 0)).max() < 20
    up, hw = read_photo(folder / "exif6.jpg")  # stored 40 wide x 20 high, left half red
    assert up.shape == (40, 20, 3) and hw == (40, 20)  # upright: 20 wide x 40 high ...
    assert up[2, 10, 0] > 200 and up[2, 10, 2] < 60  # ... the red half on top
    assert up[-3, 10, 2] > 200 and up[-3, 10, 0] < 60


@pytest.mark.usefixtures("locked")
def test_bad_files_are_refused_with_the_file_and_the_reason(folder):
    for name, reason in BAD.items():
        with pytest.raises(PsdError) as e:
            read_photo(folder / name)
        assert str(folder / name) in str(e.value) and reason in str(e.value), (name, str(e.value))


def test_a_bomb_is_refused_from_its_header_quickly_without_decoding(folder, monkeypatch):
    from PIL import ImageFile

    def no_decoding(self, *a, **k):
        raise AssertionError("pixels were decoded")

    monkeypatch.setattr(ImageFile.ImageFile, "load", no_decoding)
    (folder / "warn.png").write_bytes(png_bytes(10000, 10000))  # between PIL's warning and error limits
    for name in ("bomb.png", "warn.png"):
        t0 = time.perf_counter()
        with pytest.raises(PsdError, match="decompression bomb"):
            read_photo(folder / name)
        assert time.perf_counter() - t0 < 0.5
    with pytest.raises(PsdError, match=r"header declares 40 x 30 = 1,200 pixels, more than the limit of 1,000"):
        with open_image(folder / "good.png", max_pixels=1000):
            pass


def test_a_huge_jpeg_is_decoded_reduced_by_the_decoder(tmp_path, monkeypatch):
    """Above the reduce threshold a JPEG is decoded at 1/8 scale (Image.draft), never at full
    size, and keeps at least twice the pixels the network needs; a PNG is reduced after decoding."""
    big = save(two_halves(1600, 1200), tmp_path / "big.jpg", quality=90)
    seen = []
    real = Image.Image.reduce
    monkeypatch.setattr(Image.Image, "reduce", lambda self, f, *a: seen.append(self.size) or real(self, f, *a))
    img, hw = read_photo(big, need=lambda h, w: (32, 32), reduce_above=1_000_000)
    assert hw == (1200, 1600) and seen == [(200, 150)]  # the decoder gave 1/8 scale, reduce did the rest
    assert img.shape == (75, 100, 3) and min(img.shape[:2]) >= 2 * 32
    assert img[10, 5, 0] > 200 and img[10, -5, 2] > 200
    png = save(two_halves(1200, 900), tmp_path / "big.png")
    img, hw = read_photo(png, need=lambda h, w: (32, 32), reduce_above=1_000_000)
    assert hw == (900, 1200) and img.shape == (70, 93, 3) and min(img.shape[:2]) >= 2 * 32
    img, _ = read_photo(png, need=lambda h, w: (32, 32))  # under the default threshold: as it is
    assert img.shape == (900, 1200, 3)
    assert reduce_factor((900, 1200), (32, 32), 10**9) == 1 and reduce_factor((900, 1200), (300, 300), 1) == 1


def test_a_reduced_image_keeps_its_scale():
    from psdfactory.deploy.predict import prepare

    full = np.zeros((1200, 1600, 3), np.uint8)
    reduced = np.zeros((75, 100, 3), np.uint8)
    for mm in (None, 0.4):
        assert prepare(reduced, META, mm, size_hw=(1200, 1600)).shape == prepare(full, META, mm).shape
    with pytest.raises(PsdError, match="more than the 16,777,216 px the network is run on"):
        prepare(reduced, META, 10.0, size_hw=(1200, 1600))


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    """An untrained (random) resnet18 at 32 px, saved as training saves it: enough to run predict."""
    from psdfactory.learn.models import TargetStats, build_model
    from psdfactory.learn.runtime import save_model

    torch.manual_seed(0)
    model, _ = build_model("resnet18", TargetStats(**META["target_stats"]), "none", size=32)
    path = tmp_path_factory.mktemp("model") / "model.pt"
    save_model(path, model, META)
    return path


@pytest.mark.usefixtures("locked")
def test_predict_on_a_hostile_folder_names_each_bad_file_and_predicts_the_rest(folder, model_file, tmp_path, capsys):
    from psdfactory.cli import main

    out = tmp_path / "psd.csv"
    t0 = time.perf_counter()
    assert main(["predict", "--model", str(model_file), "--mm-per-px", "0.5", "--out", str(out), str(folder)]) == 1
    assert time.perf_counter() - t0 < 20
    rows = {Path(r["image"]).name: r for r in csv.DictReader(open(out))}
    assert set(rows) == {p.name for p in folder.iterdir()}
    for name, r in rows.items():
        if name in BAD:
            assert r["d50_mm"] == "" and name in r["error"] and BAD[name] in r["error"], (name, r)
        else:
            assert r["error"] == "" and float(r["d10_mm"]) <= float(r["d50_mm"]) <= float(r["d90_mm"]), (name, r)
    assert not (tmp_path / "psd.csv.partial.csv").exists()
    err = capsys.readouterr().err
    assert f"{len(BAD)} of {len(rows)} images failed" in err and "images/s" in err


# ---- a folder of many images: streamed, written as it goes, resumed ---------------------------

STUB = """
import time
import numpy as np
from psdfactory.deploy import predict
from psdfactory.learn.cnn import CnnRegressor

META = {meta!r}

def load_predictor(model_path, device="cpu", runtime="torch"):
    def run(x):
        time.sleep({sleep})
        m = float(x.mean())
        return np.array([[m, m + 1.0, m + 2.0]])
    return CnnRegressor(META, run)
"""
INSTALL_STUB = "predict.load_predictor = load_predictor\n"


def stub_predictor(monkeypatch, calls: list):
    ns: dict = {}
    exec(STUB.format(meta=META, sleep=0), ns)
    inner = ns["load_predictor"]

    def counting(model_path, device="cpu", runtime="torch"):
        est = inner(model_path, device)
        run = est.run
        est.run = lambda x: calls.append(1) or run(x)
        return est

    from psdfactory.deploy import predict

    monkeypatch.setattr(predict, "load_predictor", counting)


def many_images(d: Path, n: int, size: int = META["image_resolution"]) -> Path:
    d.mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        Image.fromarray(rng.integers(0, 256, (size, size, 3), dtype=np.uint8)).save(d / f"img-{i:04d}.png")
    return d


def test_300_images_stream_to_the_out_file_survive_kill_9_and_resume(tmp_path, monkeypatch, capsys):
    from psdfactory.cli import main

    imgs = many_images(tmp_path / "imgs", 300)
    out = tmp_path / "psd.csv"
    partial = tmp_path / "psd.csv.partial.csv"
    # a real process, killed with SIGKILL part-way: the rows it finished are in the partial file
    script = STUB.format(meta=META, sleep=0.01) + INSTALL_STUB + textwrap.dedent(f"""
        from psdfactory.cli import main
        main(["predict", "--model", "stub.pt", "--out", {str(out)!r}, {str(imgs)!r}])
    """)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1] / "src"))
    proc = subprocess.Popen([sys.executable, "-c", script], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 60
    while time.time() < deadline and (not partial.exists() or partial.read_text().count("\n") < 101):
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode()[-2000:]
    assert not out.exists()  # the final file appears only when every image is done
    kept = list(csv.DictReader(open(partial)))
    assert 100 <= len(kept) < 300 and all(r["error"] == "" for r in kept[:-1])

    calls: list = []
    stub_predictor(monkeypatch, calls)
    capsys.readouterr()
    assert main(["predict", "--model", "stub.pt", "--out", str(out), "--resume", str(imgs)]) == 0
    assert 300 - len(kept) <= len(calls) <= 300 - len(kept) + 1  # + a last row the kill may have cut
    err = capsys.readouterr().err
    assert f"--resume: {len(kept)}" in err or f"--resume: {len(kept) - 1}" in err
    assert "predict: 300/300 images" in err and "images/s" in err and "ETA" in err
    assert not partial.exists()
    # the same file as an uninterrupted run
    calls.clear()
    assert main(["predict", "--model", "stub.pt", "--out", str(tmp_path / "straight.csv"), str(imgs)]) == 0
    assert len(calls) == 300
    assert out.read_bytes() == (tmp_path / "straight.csv").read_bytes()
    # a second --resume has nothing left to predict; JSON out works the same way
    calls.clear()
    assert main(["predict", "--model", "stub.pt", "--out", str(out), "--resume", str(imgs)]) == 0
    assert not calls and out.read_bytes() == (tmp_path / "straight.csv").read_bytes()
    assert main(["predict", "--model", "stub.pt", "--out", str(tmp_path / "p.json"), str(imgs)]) == 0
    rows = json.loads((tmp_path / "p.json").read_text())
    assert len(rows) == 300 and isinstance(rows[0]["d50_mm"], float) and rows[0]["error"] == ""


def test_memory_stays_flat_over_a_folder(tmp_path, monkeypatch):
    """No list of decoded images: the numpy memory peak of 300 images of 96² px (8 MB in all)
    stays that of a few images."""
    import tracemalloc

    from psdfactory.deploy.predict import stream_predictions

    imgs = many_images(tmp_path / "imgs", 300, size=96)
    stub_predictor(monkeypatch, [])
    tracemalloc.start()
    n, failed = stream_predictions(Path("stub.pt"), [str(imgs)], tmp_path / "p.csv", progress_stream=io.StringIO(),
                                   mm_per_px=META["mm_per_px"])
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert (n, failed) == (300, 0)
    assert peak < 300 * 96 * 96 * 3 / 4, peak


def test_progress_line():
    from psdfactory.deploy.predict import Progress, progress_line

    assert progress_line(120, 300, 1, 4.0, 120) == "predict: 120/300 images (1 failed), 30.0 images/s, ETA 0:00:06"
    assert progress_line(0, 300, 0, 0.0, 0) == "predict: 0/300 images, 0.0 images/s, ETA ?"
    s = io.StringIO()
    p = Progress(3, s, interval=3600)
    for _ in range(3):
        p.update(False, True)
    assert s.getvalue().count("\n") == 1 and "3/3 images" in s.getvalue()  # not a tty: whole lines, the last always


def test_a_model_reads_the_size_definitions_it_can_and_refuses_the_others():
    from psdfactory import PsdError
    from psdfactory.deploy.predict import reading

    cnn = {"arch": "resnet50", "size_definition": "sieve", "weighting": "number"}
    assert reading(cnn, None) == {"size_definition": "sieve", "weighting": "number"}
    refusal = r"reads sieve \(trained on sieve labels\); train one with labels.size_definition: esd"
    with pytest.raises(PsdError, match=refusal):
        reading(cnn, "esd")
    inst = {"arch": "instances", "size_definition": "sieve", "weighting": "volume", "readouts": {"esd": {}}}
    assert reading(inst, "esd") == {"size_definition": "esd", "weighting": "volume"}
    assert reading(inst, "feret-max")["size_definition"] == "feret-max"  # measured on the grains it finds
    with pytest.raises(PsdError, match="reads sieve, esd, feret-min, feret-max, ecd"):
        reading(inst, "c-axis")  # no read-out for it
    assert reading({"arch": "resnet50"}, None)["size_definition"] == "b-axis"  # a model from before names


def test_predict_refuses_an_unknown_size_definition_in_one_line(capsys):
    from psdfactory.cli import main

    with pytest.raises(SystemExit) as e:
        main(["predict", "--model", "m.pt", "--size-definition", "diameter", "a.png"])
    assert e.value.code == 2 and "invalid choice: 'diameter'" in capsys.readouterr().err


def test_a_reading_that_is_no_size_distribution_is_named_in_a_warning(folder, model_file, tmp_path, monkeypatch,
                                                                       caplog, capsys):
    """A regressor far from its training images can read a size <= 0: predict keeps the row and
    says, naming the image, that these d-values are no measurement."""
    from psdfactory.cli import main
    from psdfactory.deploy import predict
    from psdfactory.learn.cnn import CnnRegressor

    assert predict.not_a_psd(np.array([1.0, 2.0, 3.0])) is None
    assert "a size <= 0" in predict.not_a_psd(np.array([-8.9, 0.9, 6.5]))
    assert "not a number" in predict.not_a_psd(np.array([np.nan, 1.0, 2.0]))
    assert "out of order" in predict.not_a_psd(np.array([3.0, 2.0, 4.0]))
    outputs = iter([[[-2.0, 1.0, 3.0]], [[1.0, 2.0, 3.0]]])
    monkeypatch.setattr(predict, "load_predictor",
                        lambda *a, **k: CnnRegressor(META, lambda x: np.array(next(outputs))))
    images = many_images(tmp_path / "two", 2)
    out = tmp_path / "psd.csv"
    with caplog.at_level("WARNING", logger="psdfactory.deploy.predict"):
        assert main(["predict", "--model", str(model_file), "--out", str(out), str(images)]) == 0
    rows = list(csv.DictReader(open(out)))
    assert [float(r["d10_mm"]) for r in rows] == [-2.0, 1.0] and all(r["error"] == "" for r in rows)
    warned = [r.message for r in caplog.records if "no measurement" in r.message]
    assert len(warned) == 1 and "img-0000.png" in warned[0] and "-2 / 1 / 3 mm, a size <= 0" in warned[0]
    # the table on stdout marks it, and the file says it too, beside the reading (without the path the image
    # column gives)
    printed = [ln for ln in capsys.readouterr().out.splitlines() if "img-000" in ln]
    assert "⚠ " in printed[0] and "a size <= 0" in printed[0] and "⚠" not in printed[1]
    assert rows[0]["warning"] == warned[0].split("img-0000.png: ", 1)[1] and rows[1]["warning"] == ""
    # a predictions file of before the warning column is read back by --resume as it was
    old = tmp_path / "old.csv"
    with open(old, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=[c for c in predict.COLUMNS if c != "warning"])
        w.writeheader()
        w.writerows({k: v for k, v in r.items() if k != "warning"} for r in rows)
    assert [r["warning"] for r in predict.read_rows(old)] == ["", ""]
    assert [r["d10_mm"] for r in predict.read_rows(old)] == [-2.0, 1.0]


def test_a_reading_whose_grains_lie_outside_the_readouts_fit_is_named_in_a_warning(folder, model_file, tmp_path,
                                                                                   monkeypatch, caplog):
    """The instance estimator names the statistics its read-out extrapolates from (readout_outside);
    predict says so for the image, and whether the reading was held."""
    from types import SimpleNamespace

    from psdfactory.cli import main
    from psdfactory.deploy import predict
    from psdfactory.learn.cnn import CnnRegressor
    from psdfactory.learn.estimator import Reading

    est = CnnRegressor(META, lambda x: np.array([[1.0, 2.0, 3.0]]))
    est.readout_held = True
    monkeypatch.setattr(predict, "load_predictor", lambda *a, **k: est)
    outside = ("d50_mm 35.3 (fitted 7.62 to 11.7)", "d90_mm 79.8 (fitted 13.8 to 18.9)")
    grains = iter([SimpleNamespace(readout_outside=outside), SimpleNamespace(readout_outside=())])
    monkeypatch.setattr(predict, "read_at_scale",
                        lambda *a, **k: (Reading(np.array([1.0, 2.0, 3.0]), grains=next(grains)), (32, 32)))
    images = many_images(tmp_path / "two", 2)
    with caplog.at_level("WARNING", logger="psdfactory.deploy.predict"):
        assert main(["predict", "--model", str(model_file), "--out", str(tmp_path / "psd.csv"), str(images)]) == 0
    warned = [r.message for r in caplog.records if "read-out was fitted on" in r.message]
    assert len(warned) == 1 and "img-0000.png" in warned[0] and outside[0] in warned[0] and outside[1] in warned[0]
    assert "extrapolates, held to the correction" in warned[0]


def _grains(mask: np.ndarray):
    from types import SimpleNamespace

    from psdfactory.learn.instances.measure import measure_instances

    return SimpleNamespace(measurements=measure_instances(mask, 0.5), readout_outside=())


def _grid_mask(n: int, size: int = 96) -> np.ndarray:
    """n 4 x 4 px grains, none touching the edge."""
    mask = np.zeros((size, size), np.uint16)
    for k in range(n):
        r, c = divmod(k, 12)
        mask[2 + 7 * r:6 + 7 * r, 2 + 7 * c:6 + 7 * c] = k + 1
    return mask


def test_grain_count_problem_by_hand():
    from psdfactory.deploy.predict import MIN_WHOLE_GRAINS, grain_count_problem

    assert grain_count_problem("p.jpg", None) == (None, None)  # a regressor: no grains to count
    error, warning = grain_count_problem("p.jpg", _grains(np.zeros((32, 32), np.uint16)))
    assert error.startswith("p.jpg: no grain found") and warning is None
    edge = np.zeros((32, 32), np.uint16)
    edge[:, :20] = 1  # one grain, cut by the border
    error, warning = grain_count_problem("p.jpg", _grains(edge))
    assert "every grain found (1) touches the image's edge" in error and warning is None
    error, warning = grain_count_problem("p.jpg", _grains(_grid_mask(MIN_WHOLE_GRAINS - 1)))
    assert error is None and f"{MIN_WHOLE_GRAINS - 1} whole grains found" in warning
    assert grain_count_problem("p.jpg", _grains(_grid_mask(MIN_WHOLE_GRAINS))) == (None, None)


def test_predict_refuses_a_reading_from_no_whole_grain_and_warns_on_few(folder, model_file, tmp_path, monkeypatch,
                                                                          caplog):
    """A blank or featureless image can come out as one grain filling the frame, or none at all: its
    read-out would be the training scenes' prior (a uniform grey photo read 16 / 55 / 57 mm). predict
    gives those rows an error naming the image and what to check, and warns where few grains carry it."""
    from psdfactory.cli import main
    from psdfactory.deploy import predict
    from psdfactory.learn.cnn import CnnRegressor
    from psdfactory.learn.estimator import Reading

    monkeypatch.setattr(predict, "load_predictor",
                        lambda *a, **k: CnnRegressor(META, lambda x: np.array([[1.0, 2.0, 3.0]])))
    edge = np.zeros((96, 96), np.uint16)
    edge[10:, :] = 1
    masks = iter([np.zeros((96, 96), np.uint16), edge, _grid_mask(5), _grid_mask(40)])
    monkeypatch.setattr(predict, "read_at_scale",
                        lambda *a, **k: (Reading(np.array([1.0, 2.0, 3.0]), grains=_grains(next(masks))), (96, 96)))
    images = many_images(tmp_path / "four", 4)
    out = tmp_path / "psd.csv"
    with caplog.at_level("WARNING", logger="psdfactory.deploy.predict"):
        assert main(["predict", "--model", str(model_file), "--out", str(out), str(images)]) == 1
    rows = list(csv.DictReader(open(out)))
    errors = [r["error"] for r in rows]
    assert "img-0000.png: no grain found" in errors[0] and rows[0]["d50_mm"] == ""
    assert "img-0001.png: every grain found (1) touches the image's edge" in errors[1]
    assert errors[2:] == ["", ""] and float(rows[2]["d50_mm"]) == 2.0
    warned = [r.message for r in caplog.records if "whole grain" in r.message]
    assert len(warned) == 1 and "img-0002.png: 5 whole grains found" in warned[0]
