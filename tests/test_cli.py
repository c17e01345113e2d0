import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from psdfactory import config as psd_config
from psdfactory.cli import main


def _label_args(cfg, d):
    return ["label", "--params", json.dumps(psd_config.label_params(cfg)), str(d)]


def _files(d: Path) -> dict[str, bytes]:
    return {p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_corrupt_mask_gives_clear_error(tiny_results, tmp_path, capsys):
    cfg, root = tiny_results
    d = tmp_path / "tiny-000000"
    shutil.copytree(root / "tiny" / "scenes" / "tiny-000000", d)
    (d / "mask.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    before = _files(d)
    assert main(_label_args(cfg, d)) == 2
    err = capsys.readouterr().err
    assert "mask.png is not a readable image" in err and "Traceback" not in err
    assert _files(d) == before  # the old labels untouched, no temporary file left behind


@pytest.mark.slow
def test_missing_input_gives_clear_error(tiny_results, tmp_path, capsys):
    cfg, root = tiny_results
    d = tmp_path / "tiny-000000"
    shutil.copytree(root / "tiny" / "scenes" / "tiny-000000", d)
    (d / "poses.parquet").unlink()
    (d / "labels.json").unlink()
    assert main(_label_args(cfg, d)) == 2
    err = capsys.readouterr().err
    assert f"{d}: missing poses.parquet" in err and not (d / "labels.json").exists()  # names the scene folder


def test_bad_params_json(tmp_path, capsys):
    assert main(["sample", "--params", "{not json", str(tmp_path)]) == 2
    assert "--params is not valid JSON" in capsys.readouterr().err


def test_cli_entry_point_runs_without_torch():
    exe = Path(sys.executable).with_name("psdfactory")
    r = subprocess.run(
        [sys.executable, "-X", "importtime", "-c",
         "import psdfactory.cli, psdfactory.scene.stages, psdfactory.scene.sampling, "
         "psdfactory.scene.physics, psdfactory.scene.render, psdfactory.scene.labels, psdfactory.scene.show"],
        capture_output=True, text=True,
    )
    assert r.returncode == 0 and "import time:" in r.stderr, r.stderr[-2000:]  # (an import error has no torch either)
    assert "torch" not in r.stderr  # the scene half: a scene job starts without torch
    r = subprocess.run([str(exe), "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and "psdfactory" in r.stdout


@pytest.mark.slow
def test_show_contact_sheet(tiny_results, tmp_path):
    from psdfactory.manifest import write_shard
    from psdfactory.scene.show import contact_sheet

    _, root = tiny_results
    res = tmp_path / "res"
    shutil.copytree(root, res)
    dirs = sorted((res / "tiny" / "scenes").iterdir())
    m = res / "tiny" / "manifest"
    write_shard(dirs, res, {"train": 1.0}, m / "scenes" / "shard-00000.parquet",
                m / "particles" / "shard-00000.parquet")
    out = contact_sheet(res, "tiny", tmp_path / "sheet.png", n=2)
    from PIL import Image

    with Image.open(out) as im:
        assert im.size[0] > 300 and im.size[1] > 300


def _log_lines(err: str, level: str) -> list[str]:
    return [line for line in err.splitlines() if f" {level} psdfactory.scene.stages: " in line]


@pytest.mark.parametrize("flags, shown, hidden", [([], ["INFO", "WARNING"], ["DEBUG"]),
                                                  (["--quiet"], ["WARNING"], ["INFO", "DEBUG"]),
                                                  (["-v"], ["DEBUG", "INFO", "WARNING"], [])])
def test_log_levels_flags_and_format(tmp_path, capsys, flags, shown, hidden):
    import logging
    import re

    assert main([*flags, "check-config", str(tmp_path / "none.yaml")]) == 2  # configures logging, then fails
    log = logging.getLogger("psdfactory.scene.stages")  # any module's logger
    for level in ("DEBUG", "INFO", "WARNING"):
        log.log(getattr(logging, level), f"a {level.lower()} record")
    out, err = capsys.readouterr()
    assert out == ""  # log records go to stderr (the rules send it to the job's log file)
    assert "psdfactory check-config: error: config file not found" in err  # the verdict, at any level
    for level in shown:
        (line,) = _log_lines(err, level)
        when = r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d"
        assert re.match(rf"{when} {level} psdfactory\.scene\.stages: a {level.lower()} record$", line), line
    for level in hidden:
        assert not _log_lines(err, level)
    assert bool(re.search(r"DEBUG psdfactory\.cli: psdfactory .*arguments", err)) == ("DEBUG" in shown)


def test_quiet_and_verbose_exclude_each_other(capsys):
    with pytest.raises(SystemExit):
        main(["-q", "-v", "check-config", "x.yaml"])
    assert "not allowed with" in capsys.readouterr().err


def _cli(*code: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", "\n".join(["import sys", "from psdfactory import cli", *code])],
                          capture_output=True, text=True, cwd=cwd)


def test_log_takes_the_output_and_the_verdict_reaches_the_console_too(tmp_path):
    """--log FILE is the job log of every rule: libraries' output and the records go there (file
    descriptors 1 and 2, as the shell's `> log 2>&1`), the one-line verdict goes there and to the
    console, where a full disk under the log cannot swallow it."""
    r = _cli("import os", "check = cli.cmd_check_config",
             "def noisy(a): os.write(1, b'a library writes to fd 1\\n'); return check(a)",
             "cli.cmd_check_config = noisy",
             "sys.exit(cli.main(['--log', 'job.log', 'check-config', 'none.yaml']))", cwd=tmp_path)
    log = (tmp_path / "job.log").read_text()
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip() == "psdfactory check-config: error: config file not found: none.yaml"
    assert "a library writes to fd 1" in log and r.stderr.strip() in log.splitlines()

    r = _cli("def boom(a): raise KeyError('deep inside')", "cli.cmd_check_config = boom",
             "sys.exit(cli.main(['--log', 'job.log', 'check-config', 'none.yaml']))", cwd=tmp_path)
    log = (tmp_path / "job.log").read_text()
    assert r.returncode == 1
    assert r.stderr.strip() == ("psdfactory check-config: unexpected error: KeyError: 'deep inside' "
                                "(the traceback is in job.log)")
    assert "Traceback (most recent call last)" in log and "in boom" in log  # the whole story in the log

    r = _cli("sys.exit(cli.main(['--log', 'no/such/folder/job.log', 'check-config', 'none.yaml']))", cwd=tmp_path)
    assert r.returncode == 2 and "cannot write the log no/such/folder/job.log: No such file or directory" in r.stderr


def test_a_re_renders_ceiling_without_its_sources_manifests_names_the_flags(tmp_path, capsys):
    params = '{"bounds": [1, 12], "visible_min_px": 1, "reference": {"dataset": "tiny", "splits": ["train", "val"]}}'
    args = ["ceiling", "--params", params, "--dataset", "again", "--scenes", str(tmp_path / "s.parquet"),
            "--particles", str(tmp_path / "p.parquet"), "--out", str(tmp_path / "ceiling.json")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "again: its ceilings are fitted on tiny's scenes" in err and "--reference-scenes" in err
    assert not (tmp_path / "ceiling.json").exists()
