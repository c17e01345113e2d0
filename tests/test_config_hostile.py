"""Configs no factory can run are refused quickly, in one message that names the key or the file:
alias bombs (never expanded, never printed), duplicate keys, non-UTF-8 bytes, non-finite numbers,
sizes too large to plan, and results roots that would mix outputs with the filesystem's root, the
home folder or the code."""

import time
from pathlib import Path

import pytest

from psdfactory import PsdError
from psdfactory import config as psd_config
from psdfactory.cli import main

from .conftest import REPO

BASE = """\
results: {results}
datasets:
  tiny:
    n_scenes: {n}
    table_size: {table}
    count: [10, 20]
    size: {{mean: [5, 8], sigma: [2, 3], bounds: [1, 12]}}
train:
  datasets: [tiny]
"""


def write(tmp_path: Path, text: str, name: str = "c.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text) if isinstance(text, str) else p.write_bytes(text)
    return p


def refused(path: Path, *expect: str) -> str:
    t0 = time.perf_counter()
    with pytest.raises(PsdError) as e:
        psd_config.load_config(path)
    assert time.perf_counter() - t0 < 5
    msg = str(e.value)
    assert len(msg) < 2000, msg[:300]  # never the expanded document
    for x in expect:
        assert x in msg, (x, msg)
    return msg


def test_an_alias_bomb_is_refused_unexpanded(tmp_path):
    lines = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for k in "bcdefghi":
        prev = chr(ord(k) - 1)
        lines.append(f"{k}: &{k} [" + ",".join([f"*{prev}"] * 9) + "]")
    refused(write(tmp_path, "\n".join(lines) + "\n"), "aliases expand to more than 100,000")
    # the same bomb reaching validate() as data (Snakemake loads --configfile itself)
    x: list = ["lol"] * 9
    for _ in range(8):
        x = [x] * 9
    with pytest.raises(PsdError, match="expands .* to more than 100,000 values"):
        psd_config.validate({"datasets": {}, "bomb": x})


def test_a_few_aliases_are_fine(tmp_path):
    text = BASE.format(results="results", n=2, table=60) + "render: &r {resolution: 64}\nshow: {n_scenes: 2}\n"
    text += "labels: {visible_min_px: 1}\n"
    assert psd_config.load_config(write(tmp_path, text))["render"]["resolution"] == 64


def test_duplicate_keys_and_other_bytes(tmp_path):
    dup = BASE.format(results="results", n=2, table=60) + "seed: 1\nseed: 2\n"
    refused(write(tmp_path, dup), "key 'seed' appears twice", "keep one")
    refused(write(tmp_path, "results: r\xe9sultats\n".encode("latin-1")), "is not UTF-8 text")
    assert main(["check-config", str(tmp_path / "c.yaml")]) == 2


@pytest.mark.parametrize("value,key", [(".nan", "datasets.tiny.table_size"), (".inf", "datasets.tiny.table_size"),
                                       ("-.inf", "datasets.tiny.table_size")])
def test_non_finite_numbers_are_refused_by_key(tmp_path, value, key):
    refused(write(tmp_path, BASE.format(results="results", n=2, table=value)), key, "not a finite number")


def test_non_finite_anywhere(tmp_path):
    text = BASE.format(results="results", n=2, table=60) + "  lr: .nan\n"
    refused(write(tmp_path, text), "train.lr", "not a finite number")
    text = BASE.format(results="results", n=2, table=60).replace("mean: [5, 8]", "mean: [.nan, 8]")
    refused(write(tmp_path, text), "datasets.tiny.size.mean[0]")


def test_sizes_too_large_to_plan_are_refused_at_once(tmp_path):
    refused(write(tmp_path, BASE.format(results="results", n=10**12, table=60)), "datasets.tiny.n_scenes")
    big = BASE.format(results="results", n=10**7, table=60)
    refused(write(tmp_path, big), "scene jobs", "raise scenes_per_job to at least 160")
    assert psd_config.load_config(write(tmp_path, big + "scenes_per_job: 200\n"))["scenes_per_job"] == 200
    rerender = big.replace("train:", "  again:\n    rerender_of: {dataset: tiny}\n    n_scenes: 10000000\ntrain:")
    refused(write(tmp_path, rerender), "scene jobs")
    text = BASE.format(results="results", n=2, table=60) + "  input_size: {resnet50: 1000000}\n"
    refused(write(tmp_path, text), "train.input_size.resnet50")


@pytest.mark.parametrize("results,says", [('""', "must name a folder"), ("/", "filesystem root"),
                                          ("'~'", "home folder itself"), (str(REPO / "src"), "mix with the code"),
                                          (str(REPO / "config" / "out"), "mix with the code"),
                                          (str(REPO), "the source checkout")])
def test_results_roots_that_mix_outputs_with_other_things_are_refused(tmp_path, results, says):
    refused(write(tmp_path, BASE.format(results=results, n=2, table=60)), "results:", says)


def test_the_default_results_root_is_fine():
    assert psd_config.load_config(REPO / "config" / "config.yaml")["results"] == "results"


def test_an_unknown_architecture_is_refused_before_any_scene(tmp_path, capsys):
    from psdfactory.learn.registry import check_architectures

    check_architectures(["instances"], known=lambda: set())  # never asks torchvision
    check_architectures(["resnet50", "instances"], known=lambda: {"resnet50", "resnet18"})
    with pytest.raises(PsdError, match=r"'resnet5000' not an estimator .* e.g. resnet18, resnet50"):
        check_architectures(["resnet5000"], known=lambda: {"resnet50", "resnet18"})
    text = BASE.format(results="results", n=2, table=60) + "  architectures: [resnet50, nosuchnet]\n"
    assert main(["check-config", str(write(tmp_path, text))]) == 2
    err = capsys.readouterr().err
    assert "train.architectures: 'nosuchnet' not an estimator" in err and len(err.strip().splitlines()) == 1


@pytest.mark.workflow
def test_the_workflow_reads_its_config_files_as_strictly(tmp_path):
    from .workflow_helpers import snakemake

    text = BASE.format(results="results", n=2, table=60)
    for name, body, says in (("dup.yaml", text + "seed: 1\nseed: 2\n", "key 'seed' appears twice"),
                             ("nan.yaml", text.replace("table_size: 60", "table_size: .nan"), "not a finite number")):
        r = snakemake("-n", "--configfile", str(write(tmp_path, body, name)), workdir=tmp_path)
        out = r.stdout + r.stderr  # (Snakemake prints its errors to stdout)
        assert r.returncode != 0 and says in out, out[-1500:]
        assert "Traceback" not in out
