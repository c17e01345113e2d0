"""`snakemake --profile slurm` on a real single-node SLURM cluster (slurm/cluster.sh).

Marked `slurm`; CI runs it. It needs root (the script installs and starts slurmctld, slurmd,
slurmdbd, munge and a private MariaDB).
"""

import copy
import filecmp
import os
import subprocess
import time

import pyarrow.parquet as pq
import pytest

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
    env = dict(os.environ, PSD_SLURM_DIR=STATE, **ports)
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
