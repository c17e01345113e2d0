"""`snakemake --profile slurm` on a real single-node SLURM cluster (slurm/cluster.sh).

Marked `slurm`; CI runs it. It needs root (the script installs and starts slurmctld, slurmd,
slurmdbd, munge and a private MariaDB). The cluster's node declares two GPUs (gres/gpu, stand-in
devices), so the profile's GPU jobs are submitted, scheduled and accounted as on a GPU cluster,
and run on the CPU.
"""

import copy
import filecmp
import json
import logging
import os
import re
import subprocess
import time

import pyarrow.parquet as pq
import pytest
import yaml

from .workflow_helpers import REPO, snakemake, write_config

pytestmark = [pytest.mark.slurm, pytest.mark.workflow]

CLUSTER = REPO / "slurm" / "cluster.sh"
STATE = "/var/tmp/psdfactory-slurm-test"

TINY = {
    "seed": 5,
    "datasets": {"train": {"n_scenes": 3, "shard_size": 2, "table_size": 40, "count": [8, 12],
                           "size": {"mean": [4, 6], "sigma": [1, 2], "bounds": [1, 8]}}},
    "render": {"resolution": 32},
}


def free_ports(n: int) -> list[int]:
    """n TCP ports free on 127.0.0.1 now (the kernel's picks, held together so they differ)."""
    import socket

    socks = [socket.socket(socket.AF_INET, socket.SOCK_STREAM) for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def other_cluster() -> str | None:
    """The state folder of a cluster.sh cluster of another state folder running here (the one a
    user brought up as the README says), or None."""
    conf = os.path.realpath("/etc/slurm/slurm.conf")
    state = os.path.dirname(os.path.dirname(conf))
    if not conf.startswith("/") or state == STATE or not os.path.isfile(f"{state}/run/slurmctld.pid"):
        return None
    try:
        os.kill(int(open(f"{state}/run/slurmctld.pid").read().strip()), 0)
    except (OSError, ValueError):
        return None
    return state


@pytest.fixture(scope="module")
def cluster():
    if os.geteuid() != 0:
        pytest.skip("bringing up SLURM needs root")
    if other_cluster():  # its jobs' steps would read that cluster's /etc/slurm/slurm.conf
        pytest.skip(f"another SLURM cluster runs here ({other_cluster()}): the test cluster runs only on a machine "
                    f"without one; `PSD_SLURM_DIR={other_cluster()} slurm/cluster.sh down` to run these tests")
    # its own ports, so that it runs beside a cluster the user brought up (slurm/cluster.sh up)
    ports = dict(zip(("PSD_SLURM_DB_PORT", "PSD_SLURM_CTLD_PORT", "PSD_SLURM_SLURMD_PORT", "PSD_SLURM_DBD_PORT"),
                     map(str, free_ports(4)), strict=True))
    env = dict(os.environ, PSD_SLURM_DIR=STATE, PSD_SLURM_GPUS="2", **ports)  # two GPU jobs side by side
    up = subprocess.run(["bash", str(CLUSTER), "up"], env=env, capture_output=True, text=True, timeout=1200)
    if up.returncode != 0:  # leave no half-started daemons behind for the next run
        subprocess.run(["bash", str(CLUSTER), "down"], env=env, capture_output=True, text=True, timeout=120)
    assert up.returncode == 0, up.stdout + up.stderr
    env["SLURM_CONF"] = f"{STATE}/etc/slurm.conf"
    env.update(PSD_SLURM_ACCOUNT="psdfactory", PSD_SLURM_PARTITION="local", PSD_SLURM_GPU_PARTITION="local")
    yield env
    subprocess.run(["bash", str(CLUSTER), "down"], env=env, capture_output=True, text=True, timeout=120)


def sacct_states(env, since: str) -> list[tuple[str, str]]:
    r = subprocess.run(["sacct", "-X", "-n", "-P", "-S", since, "-o", "JobName,State"], env=env,
                       capture_output=True, text=True, check=True)
    return [tuple(line.split("|")[:2]) for line in r.stdout.splitlines() if line.strip()]


BATCH_RULES = ("sample_batch", "simulate_batch", "render_batch", "label_batch")


@pytest.mark.parametrize("per_job", [1, 2], ids=["one-job-per-scene", "batches-of-2"])
def test_scene_stages_run_through_slurm_and_match_a_local_run(cluster, tmp_path, per_job):
    since = time.strftime("%Y-%m-%dT%H:%M:%S")
    slurm_work, local_work = tmp_path / "slurm", tmp_path / "local"
    for w in (slurm_work, local_work):
        w.mkdir()
    tiny = dict(copy.deepcopy(TINY), scenes_per_job=per_job)
    cfg = write_config(slurm_work / "c.yaml", dict(tiny, results=str(slurm_work / "results")))
    # the profile's batch jobs ask for 4 CPUs; this test cluster's one node has 2
    small_node = ["--set-resources", *(f"{r}:cpus_per_task=2" for r in BATCH_RULES),
                  "--set-threads", *(f"{r}=2" for r in BATCH_RULES)] if per_job > 1 else []
    r = snakemake("scenes", "--profile", str(REPO / "slurm"), "--configfile", str(cfg),
                  "--slurm-init-seconds-before-status-checks", "2", "--latency-wait", "10", *small_node,
                  workdir=slurm_work, env=cluster)
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    states = sacct_states(cluster, since)
    assert states, "sacct shows no jobs: nothing went through SLURM"
    assert all(s == "COMPLETED" for _, s in states), states
    if per_job > 1:  # 2 batches per stage + manifests + contact sheet, each its own SLURM job
        assert len(states) >= 4 * 2
        log = (slurm_work / "results" / "train" / "logs" / "simulate" / "batch-00000.log").read_text()
        assert "2 of 2 scenes to run" in log

    cfg = write_config(local_work / "c.yaml", dict(copy.deepcopy(TINY), results=str(local_work / "results")))
    r = snakemake("-j2", "scenes", "--configfile", str(cfg), workdir=local_work)
    assert r.returncode == 0, r.stderr[-3000:]
    a = pq.read_table(slurm_work / "results" / "train" / "manifest" / "scenes").sort_by("scene_id")
    b = pq.read_table(local_work / "results" / "train" / "manifest" / "scenes").sort_by("scene_id")
    cols = [c for c in a.column_names if c not in ("image_path", "mask_path")]
    assert a.select(cols).equals(b.select(cols))
    for i in range(3):
        for f in ("image.png", "mask.png", "poses.parquet"):
            sa = slurm_work / "results" / "train" / "scenes" / f"train-{i:06d}" / f
            sb = local_work / "results" / "train" / "scenes" / f"train-{i:06d}" / f
            if f.endswith(".png"):
                assert filecmp.cmp(sa, sb, shallow=False), f"{f} of scene {i} differs"


def test_failing_job_is_retried_then_the_run_fails(cluster, tmp_path):
    since = time.strftime("%Y-%m-%dT%H:%M:%S")
    cfg = copy.deepcopy(TINY)
    cfg["datasets"]["train"]["n_scenes"] = 1
    cfg["physics"] = {"max_time_s": 0.01, "retries": 0, "quality": {"min_settled_fraction": 1.0}}
    cfg["results"] = str(tmp_path / "results")
    cfgfile = str(write_config(tmp_path / "c.yaml", cfg))
    r = snakemake("scenes", "--profile", str(REPO / "slurm"), "--configfile", cfgfile,
                  "--slurm-init-seconds-before-status-checks", "2", "--latency-wait", "5", "--retries", "1",
                  workdir=tmp_path, env=cluster)
    assert r.returncode != 0
    failed = [n for n, s in sacct_states(cluster, since) if s == "FAILED"]
    assert len(failed) >= 2, f"expected the first try and one retry to fail on SLURM: {failed}"
    log = (tmp_path / "results" / "train" / "logs" / "simulate" / "train-000000.log").read_text()
    assert "quality bounds" in log


# ---- the whole workflow: scenes, training, evaluation, benchmark and report on SLURM ----------

GPU_RULES = ("train", "evaluate", "benchmark")

WHOLE = {  # the smallest run with a val and a test scene (seed 7: 2 train / 2 val / 1 test)
    "seed": 7,
    "scenes_per_job": 5,  # 4 batch jobs (the one job group of 20 scene jobs ran them one after another: 2.3 min)
    "datasets": {"train": {"n_scenes": 5, "shard_size": 5, "table_size": 50, "count": [20, 30],
                           "split": {"train": 0.5, "val": 0.25, "test": 0.25},
                           "size": {"mean": [4, 7], "sigma": [2, 3], "bounds": [1, 10]}}},
    "render": {"resolution": 32},
    "train": {"epochs": 1, "batch_size": 2, "precision": "fp32", "pretrained": "none",
              "architectures": ["instances"], "input_size": {"instances": 32}},  # the CNNs: test_workflow
    "benchmark": {"batch_size": 2, "seconds": 0.05, "repeats": 1},
    "show": {"compare_backends": 0, "n_scenes": 2},
}


def small_node_profile(dest):
    """slurm/config.yaml for the test cluster's one node (2 CPUs): the GPU rules keep the profile's
    GPU and partition but ask for 1 CPU (and 1 thread) and 2 GB, so that two can run side by side; the
    scene batches 2 CPUs. A copy of the profile rather than --set-resources, which would replace
    the profile's whole set-resources block."""
    prof = yaml.safe_load((REPO / "slurm" / "config.yaml").read_text())
    for rule in GPU_RULES:
        assert prof["set-resources"][rule]["gpu"] == 1, f"the profile no longer asks a GPU for {rule}"
        prof["set-resources"][rule].update(cpus_per_task=1, mem_mb=2000)
        prof["set-threads"][rule] = 1
    for rule in BATCH_RULES:
        prof["set-resources"][rule]["cpus_per_task"] = prof["set-threads"][rule] = 2
    dest.mkdir()
    (dest / "config.yaml").write_text(yaml.safe_dump(prof, sort_keys=False))
    return dest


def submitted_jobs(output: str) -> dict[str, list[str]]:
    """SLURM job ids per rule (or group), from the SLURM executor's 'submitted' lines."""
    jobs: dict[str, list[str]] = {}
    for jobid, name in re.findall(r"submitted with SLURM jobid (\d+) \(log: \S*/slurm_logs/(?:rule|group)_(\w+)/",
                                  output):
        jobs.setdefault(name, []).append(jobid)
    return jobs


def test_whole_workflow_on_slurm_gpu_jobs_get_a_gpu_and_run_on_the_cpu(cluster, tmp_path):
    cfg = write_config(tmp_path / "c.yaml", dict(copy.deepcopy(WHOLE), results=str(tmp_path / "results")))
    profile = small_node_profile(tmp_path / "profile")
    t0 = time.monotonic()
    r = snakemake("--profile", str(profile), "--configfile", str(cfg), "--slurm-init-seconds-before-status-checks",
                  "2", "--latency-wait", "10", workdir=tmp_path, env=cluster)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out[-4000:]
    print(f"whole workflow on SLURM: {time.monotonic() - t0:.0f} s")
    jobs = submitted_jobs(out)
    assert all(len(jobs.get(rule, [])) == 1 for rule in (*BATCH_RULES, "manifest_shard", *GPU_RULES, "report")), jobs
    ids = [i for found in jobs.values() for i in found]
    acct = subprocess.run(["sacct", "-X", "-n", "-P", "-j", ",".join(ids), "-o", "JobID,State,ReqTRES,AllocTRES"],
                          env=cluster, capture_output=True, text=True, check=True).stdout
    rows = {line.split("|")[0]: line.split("|")[1:] for line in acct.splitlines() if line.strip()}
    print("\n".join(f"{rule} {i} {'|'.join(rows.get(i, []))}" for rule, found in jobs.items() for i in found))
    assert set(rows) == set(ids), acct
    for rule, found in jobs.items():
        for i in found:
            state, req, alloc = rows[i]
            assert state == "COMPLETED", (rule, i, rows[i])
            gpu = rule in GPU_RULES
            assert ("gres/gpu=1" in req and "gres/gpu=1" in alloc) == gpu, (rule, i, rows[i])
    # on the CPU, and their logs say why
    res = tmp_path / "results"
    for arch in WHOLE["train"]["architectures"]:
        for log in (res / "models" / arch / "train.log", res / "eval" / arch / "evaluate.log",
                    res / "bench" / f"{arch}.log"):
            text = log.read_text()
            assert re.search(r"WARNING .*device auto: SLURM allocated GPU\(s\) to this job \(SLURM_STEP_GPUS=\d.*"
                             r"CUDA_VISIBLE_DEVICES=\d\) but CUDA sees none .*; running on the CPU", text), log
        assert json.loads((res / "eval" / arch / "metrics.json").read_text())["datasets"]["train"]
        bench = json.loads((res / "bench" / f"{arch}.json").read_text())
        assert [b["device"] for b in bench["results"]] == ["cpu"]
    assert "Inference speed" in (res / "report" / "report.html").read_text()


def test_auto_device_warns_only_where_slurm_gave_a_gpu_cuda_cannot_see(monkeypatch, caplog):
    import torch

    from psdfactory.learn.runtime import pick_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for k in ("SLURM_JOB_GPUS", "SLURM_STEP_GPUS", "SLURM_GPUS_ON_NODE"):
        monkeypatch.delenv(k, raising=False)
    with caplog.at_level(logging.WARNING, logger="psdfactory"):
        assert pick_device("auto").type == "cpu"
        monkeypatch.setenv("SLURM_GPUS_ON_NODE", "0")
        assert pick_device("auto").type == "cpu"
        assert not caplog.records  # no GPU asked for: running on the CPU is what was meant
        monkeypatch.setenv("SLURM_JOB_GPUS", "0")
        monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0")
        assert pick_device("auto").type == "cpu"
    assert [r.levelname for r in caplog.records] == ["WARNING"]
    assert "SLURM allocated GPU(s) to this job (SLURM_JOB_GPUS=0; CUDA_VISIBLE_DEVICES=0) but CUDA sees none" in \
        caplog.records[0].getMessage()


def test_a_cnn_trains_from_a_pack_on_a_nodes_two_gpus_through_sbatch(cluster, tmp_path):
    """slurm/train_ddp.sbatch: submitted with --gres=gpu:2, it runs one training process per GPU
    under torchrun (here on the CPU: the node's GPUs are stand-ins), each reading its own shards of
    the pack, and rank 0 writes one model."""
    import sys

    from psdfactory.learn.shards import pack
    from psdfactory.packs import PackSpec

    from .conftest import split_dataset

    results = tmp_path / "results"
    split_dataset(results, ["train"] * 4 + ["val"] * 2)
    pack(results, ["tiny"], tmp_path / "pack", PackSpec(size=32, shard_scenes=2))
    cfg = write_config(tmp_path / "c.yaml", {
        "results": str(results), "seed": 3, "datasets": {"tiny": {"n_scenes": 6}},
        "train": {"datasets": ["tiny"], "architectures": ["resnet18"], "pretrained": "none", "epochs": 2,
                  "batch_size": 2, "precision": "fp32", "size_cells": 0.0, "input_size": {"resnet18": 32}}})
    out, log = tmp_path / "model", tmp_path / "job.log"
    env = dict(cluster, PSD_PYTHON=sys.executable)
    r = subprocess.run(["sbatch", "--wait", "--parsable", "--gres=gpu:2", "--cpus-per-task=2", "--mem=2G",
                        "--partition", cluster["PSD_SLURM_GPU_PARTITION"], "--account", cluster["PSD_SLURM_ACCOUNT"],
                        "--output", str(log), str(REPO / "slurm" / "train_ddp.sbatch"), str(cfg), "resnet18",
                        str(tmp_path / "pack"), str(out)], env=env, capture_output=True, text=True, timeout=900)
    text = log.read_text() if log.is_file() else ""
    assert r.returncode == 0, r.stdout + r.stderr + text[-4000:]
    job = r.stdout.strip().split(";")[0]
    acct = subprocess.run(["sacct", "-X", "-n", "-P", "-j", job, "-o", "State,AllocTRES"], env=cluster,
                          capture_output=True, text=True, check=True).stdout
    assert "COMPLETED" in acct and "gres/gpu=2" in acct, acct
    assert "2 processes, 0 loader workers each" in text and "distributed training: 2 processes (gloo)" in text
    import torch

    meta = torch.load(out / "model.pt", weights_only=False)["meta"]
    assert meta["pack"]["ranks"] == 2 and meta["epochs_run"] == 2 and meta["arch"] == "resnet18"
