import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from psdfactory import cli
from psdfactory import config as psd_config
from psdfactory.cli import main
from psdfactory.psd import SIZE_DEFINITIONS


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


# ---- the command line's surface: help, groups, examples, one-line usage errors -------------------------------

def _commands(ap: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    (sub,) = (a for a in ap._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _helps(monkeypatch, columns: int) -> dict[str | None, str]:
    """`psdfactory --help` (key None) and every `psdfactory <command> --help`, in a terminal this wide."""
    monkeypatch.setenv("COLUMNS", str(columns))
    ap = cli.build_parser()
    return {None: ap.format_help(), **{name: p.format_help() for name, p in _commands(ap).items()}}


def test_every_option_of_every_command_has_help_choices_and_defaults(monkeypatch):
    monkeypatch.setenv("COLUMNS", "100")
    ap = cli.build_parser()
    for name, p in [(None, ap), *_commands(ap).items()]:
        text = " ".join(p.format_help().split())
        for a in p._actions:
            if isinstance(a, argparse._HelpAction | argparse._SubParsersAction):
                continue
            what = (name, a.option_strings or a.dest)
            assert a.help and a.help.strip() and a.help != argparse.SUPPRESS, what
            for choice in a.choices or ():
                assert choice in text, (*what, choice)  # the choices are listed
            if a.option_strings and a.default not in (None, False, [], argparse.SUPPRESS):
                assert f"(default: {a.default})" in text, what
    assert _commands(ap)["predict"]._option_string_actions["--size-definition"].choices == SIZE_DEFINITIONS


def test_user_commands_come_before_the_workflow_commands_in_the_help(monkeypatch):
    text = _helps(monkeypatch, 100)[None]
    lines = text.splitlines()
    assert set(cli.USER_COMMANDS) | set(cli.WORKFLOW_COMMANDS) == set(_commands(cli.build_parser()))
    assert not set(cli.USER_COMMANDS) & set(cli.WORKFLOW_COMMANDS)
    assert "{sample," not in text and "{predict," not in text  # no raw list of choices
    listed = {}
    for i, line in enumerate(lines):
        words = line.split()
        if line.startswith("  ") and words and words[0] in cli.COMMANDS and not line.startswith("  psdfactory"):
            assert words[0] not in listed, f"{words[0]} listed twice"
            listed[words[0]] = i
    heading = lines.index(cli.WORKFLOW_HEADING + ":")
    assert lines.index("commands:") < heading
    assert set(listed) == set(cli.COMMANDS)
    assert all(listed[c] < heading for c in cli.USER_COMMANDS), listed
    assert all(listed[c] > heading for c in cli.WORKFLOW_COMMANDS), listed
    assert [c for c in listed if c in cli.USER_COMMANDS][:2] == ["predict", "export"]


def _example_commands(text: str) -> list[list[str]]:
    """The psdfactory command lines in a help's examples, continuation lines joined, comments dropped."""
    import shlex

    block = text.split("\nexamples:\n", 1)[1].replace("\\\n", " ")
    out = []
    for line in block.splitlines():
        for part in line.split("#")[0].split("&&"):
            words = shlex.split(part)
            if words[:1] == ["psdfactory"]:
                out.append(words[1:])
    return out


@pytest.mark.parametrize("name", [None, *cli.USER_COMMANDS])
def test_the_main_help_and_each_user_command_show_examples_that_parse(monkeypatch, name):
    examples = _example_commands(_helps(monkeypatch, 100)[name])
    assert examples and (name is None or any(e[0] == name for e in examples)), examples
    if name is None:
        assert {e[0] for e in examples} >= {"predict", "export", "show", "check-config"}
    for args in examples:
        if "--help" not in args:
            ns = cli.build_parser().parse_args(args)  # the flags are real, the values valid
            assert ns.command == args[0]


@pytest.mark.parametrize("columns", [100, 200])
def test_the_help_fits_100_columns(monkeypatch, columns):
    for name, text in _helps(monkeypatch, columns).items():
        wide = [line for line in text.splitlines() if len(line) > 100]
        assert not wide, (name, wide)


def test_the_rules_call_workflow_commands_by_their_names():
    """A rule that calls a command calls one the CLI has; each workflow command's help names the rule
    file that calls it, truly."""
    import re

    from .conftest import REPO

    called: dict[str, set[str]] = {}
    for smk in sorted((REPO / "rules").glob("*.smk")):
        for cmd in re.findall(r"psdfactory --log \{log:q\} ([a-z][a-z-]*)", smk.read_text()):
            called.setdefault(cmd, set()).add(f"rules/{smk.name}")
    assert set(called) <= set(cli.COMMANDS), set(called) - set(cli.COMMANDS)
    assert set(cli.WORKFLOW_COMMANDS) <= set(called), set(cli.WORKFLOW_COMMANDS) - set(called)
    for cmd, (_, rules) in cli.WORKFLOW_COMMANDS.items():
        assert rules in called[cmd], (cmd, rules, called[cmd])


@pytest.mark.parametrize("args, says", [
    ([], "psdfactory: error: no command given (see psdfactory --help)"),
    (["predit", "photos/"], "psdfactory: error: unknown command 'predit': did you mean predict? "
                            "(see psdfactory --help)"),
    (["predict", "photos/"], "psdfactory predict: error: the following arguments are required: --model "
                             "(see psdfactory predict --help)"),
    (["show", "--frames", "3"], "psdfactory show: error: unrecognized arguments: --frames 3 "
                                "(see psdfactory show --help)"),
    (["export", "--model", "m.pt", "--out-dir", "d", "--int8-max-r2-change", "a lot"],
     "psdfactory export: error: argument --int8-max-r2-change: invalid float value: 'a lot' "
     "(see psdfactory export --help)"),
])
def test_a_bad_invocation_is_one_line_with_exit_code_2(capsys, args, says):
    with pytest.raises(SystemExit) as e:
        main(args)
    out, err = capsys.readouterr()
    assert e.value.code == 2 and out == "" and err.splitlines() == [says], err


def test_predict_with_a_missing_model_prints_one_line_and_no_table_header(tmp_path, capsys):
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.png").write_bytes(b"\x89PNG not really")
    model = tmp_path / "models" / "model.pt"
    assert main(["predict", "--model", str(model), "--out", str(tmp_path / "psd.csv"), str(tmp_path / "photos")]) == 2
    out, err = capsys.readouterr()
    assert out == ""  # no header before the error
    (line,) = err.splitlines()
    assert line.startswith("psdfactory predict: error: ") and line.endswith(f"model file not found: {model}"), line
    assert not (tmp_path / "psd.csv").exists() and not (tmp_path / "psd.csv.partial.csv").exists()
