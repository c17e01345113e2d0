"""Fail fast and say why: the checks the workflow makes before any job (psdfactory.preflight),
and that Snakemake stops with their message in seconds, having changed nothing."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
import yaml

from psdfactory import PsdError
from psdfactory.preflight import check_results, check_slurm, results_problem, unknown_name_problems, unset_env_problems

from .workflow_helpers import REPO, snakemake, write_config

SLURM_VARS = ("PSD_SLURM_ACCOUNT", "PSD_SLURM_PARTITION", "PSD_SLURM_GPU_PARTITION")


def profile_resources() -> dict:
    """slurm/config.yaml's resources as Snakemake hands them over (raw, unexpanded values)."""
    y = yaml.safe_load((REPO / "slurm" / "config.yaml").read_text())
    return {"default-resources": y["default-resources"],
            **{f"set-resources {rule}": v for rule, v in y["set-resources"].items()}}


# ---- the results folder -------------------------------------------------------------------------


def test_a_writable_results_folder_passes_and_nothing_is_created(tmp_path):
    assert results_problem(tmp_path) is None
    assert results_problem(tmp_path / "not" / "yet") is None  # created later, by the jobs
    assert not (tmp_path / "not").exists()


def test_a_results_folder_that_cannot_be_written_is_named(tmp_path):
    (tmp_path / "afile").write_text("x")
    with pytest.raises(PsdError, match=r"folder .*afile/results cannot be created: .*afile is a file, not a folder"):
        check_results(tmp_path / "afile" / "results")
    refuse = lambda path, mode: False  # noqa: E731  (as access() answers a user without permission)
    msg = results_problem(tmp_path / "res", access=refuse)
    assert f"results folder {tmp_path / 'res'} is not writable: {tmp_path} (where it would be created)" in msg
    assert "Set `results:` in the config" in msg
    (tmp_path / "res").mkdir()
    msg = results_problem(tmp_path / "res", refuse)
    assert f"{tmp_path / 'res'} is not writable: it does not let this user write" in msg


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write into any folder")
def test_a_folder_without_write_permission_is_refused(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o555)
    try:
        assert "is not writable" in results_problem(ro / "results")
    finally:
        ro.chmod(0o755)


# ---- the SLURM profile ----------------------------------------------------------------------------


def test_unset_slurm_variables_are_named_with_how_to_set_them():
    problems = unset_env_problems(profile_resources(), {})
    assert len(problems) == 3
    for var, p in zip(SLURM_VARS, problems, strict=True):
        assert f"the environment variable {var} is not set" in p and f"export {var}=<name>" in p
    assert "default-resources slurm_account: $PSD_SLURM_ACCOUNT" in problems[0] and "sacctmgr" in problems[0]
    assert "set-resources train slurm_partition: $PSD_SLURM_GPU_PARTITION" in problems[2]
    env = dict.fromkeys(SLURM_VARS, "x")
    assert unset_env_problems(profile_resources(), env) == []
    empty = {**env, "PSD_SLURM_ACCOUNT": ""}
    assert "PSD_SLURM_ACCOUNT is not set" in unset_env_problems(profile_resources(), empty)[0]
    assert "${ACC}" in unset_env_problems({"default-resources": {"slurm_account": "${ACC}"}}, {})[0]


def fake_slurm(partitions: str | None, accounts: str | None, calls: list | None = None):
    def run(cmd):
        if calls is not None:
            calls.append(cmd[0])
        return {"sinfo": partitions, "sacctmgr": accounts}[cmd[0]]

    return run


def test_partitions_and_accounts_the_cluster_does_not_know_are_refused():
    env = {"PSD_SLURM_ACCOUNT": "proj", "PSD_SLURM_PARTITION": "cpu", "PSD_SLURM_GPU_PARTITION": "gpu"}
    res = profile_resources()
    assert unknown_name_problems(res, env, "me", fake_slurm("cpu\ngpu\n", "proj\nother\n")) == []
    problems = unknown_name_problems(res, {**env, "PSD_SLURM_GPU_PARTITION": "gpus", "PSD_SLURM_ACCOUNT": "prj"}, "me",
                                     fake_slurm("cpu\ngpu\n", "proj\n"))
    assert problems[0].startswith("SLURM partition 'gpus' (set-resources train slurm_partition) does not exist on this "
                                  "cluster; sinfo lists: cpu, gpu")
    assert problems[1].startswith("SLURM account 'prj' (default-resources slurm_account) is not one of me's accounts; "
                                  "sacctmgr lists: proj")
    # where sinfo / sacctmgr cannot answer (no cluster here, no accounting): not checked
    assert unknown_name_problems(res, {**env, "PSD_SLURM_PARTITION": "zzz"}, "me", fake_slurm(None, None)) == []


def test_check_slurm_reports_unset_variables_before_asking_the_cluster():
    calls: list = []
    with pytest.raises(PsdError, match="PSD_SLURM_ACCOUNT is not set"):
        check_slurm(profile_resources(), {}, "me", fake_slurm("cpu\n", "proj\n", calls))
    assert calls == []  # no query with a literal $NAME
    check_slurm({"default-resources": {"mem_mb": 1000}}, {}, "me", fake_slurm(None, None, calls))  # not a SLURM profile
    assert calls == []


# ---- through Snakemake: each fails in seconds, with the message, and writes nothing ---------------

TINY = {"results": "results", "datasets": {"a": {"n_scenes": 2, "count": [8, 12], "table_size": 40,
                                                 "size": {"mean": [4, 6], "sigma": [1, 2], "bounds": [1, 8]}}},
        "render": {"resolution": 32}, "train": {"datasets": ["a"]}, "show": {"compare_backends": 0}}


def fails_fast(tmp_path: Path, *args: str, env: dict | None = None, cfg: dict | None = None, target: str = "scenes"):
    cfgfile = write_config(tmp_path / "c.yaml", cfg or TINY)
    t0 = time.perf_counter()
    r = snakemake("-n", target, "--configfile", str(cfgfile), *args, workdir=tmp_path, env=env)
    seconds = time.perf_counter() - t0
    assert r.returncode != 0, r.stdout[-2000:]
    assert seconds < 60, seconds  # Snakemake's start-up on a busy 2-core machine; the checks add < 0.1 s
    assert not (tmp_path / "results").exists()
    return r.stdout + r.stderr


def no_blender_env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in SLURM_VARS}
    return {**env, "PSD_BLENDER_PYTHON": "/nonexistent/blender/python"}


@pytest.mark.workflow
def test_snakemake_stops_before_any_job_on_each_misconfiguration(tmp_path):
    (tmp_path / "afile").write_text("x")
    err = fails_fast(tmp_path, "--config", f"results={tmp_path / 'afile' / 'results'}")
    assert "psdfactory: results folder" in err and "is a file, not a folder" in err

    err = fails_fast(tmp_path, "--profile", str(REPO / "slurm"), env=no_blender_env())
    for var in SLURM_VARS:
        assert f"the environment variable {var} is not set" in err and f"export {var}=<name>" in err

    cycles = {**TINY, "datasets": {"a": {**TINY["datasets"]["a"], "render": {"backend": "cycles"}}}}
    err = fails_fast(tmp_path, env=no_blender_env(), cfg=cycles)
    assert "psdfactory: dataset a renders with Cycles" in err and "/nonexistent/blender/python" in err
    assert "make blender" in err

    from .test_shapes import bad_meshes

    meshes = bad_meshes(tmp_path)
    mesh = {**TINY, "datasets": {"a": {**TINY["datasets"]["a"], "shape": "mesh",
                                       "shape_params": {"mesh_files": [str(meshes["inside_out.obj"][0])]}}}}
    err = fails_fast(tmp_path, cfg=mesh)
    assert "c.yaml: invalid config:" in err
    assert f"datasets.a.shape_params.mesh_files[0]: particle mesh {meshes['inside_out.obj'][0]} is inside out" in err

    # the report's backend comparison needs Blender only where the DAG holds it (not for `scenes`)
    err = fails_fast(tmp_path, env=no_blender_env(), cfg={**TINY, "show": {"compare_backends": 2}}, target="all")
    assert "show.compare_backends > 0" in err and "make blender" in err
    cfgfile = write_config(tmp_path / "c.yaml", {**TINY, "show": {"compare_backends": 2}})
    r = snakemake("-n", "scenes", "--configfile", str(cfgfile), workdir=tmp_path, env=no_blender_env())
    assert r.returncode == 0, r.stderr[-2000:]


@pytest.mark.workflow
def test_lint_does_not_look_at_the_machine(tmp_path):
    """--lint checks the workflow, not this machine's Blender or SLURM variables."""
    cfg = str(REPO / "config" / "config.yaml")
    r = snakemake("--lint", "--configfile", cfg, workdir=tmp_path, env=no_blender_env())
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    assert "Blender" not in r.stdout + r.stderr
