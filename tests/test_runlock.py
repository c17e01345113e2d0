"""One run per results folder: a second run on the same `results:` (from another working
directory, so Snakemake's own lock does not see it) is refused with a message naming the folder
and the run that holds it; the lock goes with its process (kill -9 leaves none); dry runs and
jobs do not take it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from psdfactory import PsdError
from psdfactory.runlock import LOCK_NAME, describe, lock_results

from .test_preflight import TINY
from .workflow_helpers import snakemake, write_config

HOLD = """
import sys, time
from psdfactory.runlock import holder, lock_results
f = lock_results(sys.argv[1], holder(["snakemake", "-j2", "--configfile", "first.yaml"]))
print("held", flush=True)
time.sleep(600)
"""


def hold_elsewhere(results: Path) -> subprocess.Popen:
    """Another process that holds the results folder's lock (as a running `snakemake` does)."""
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(results)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_the_second_taker_is_refused_naming_the_folder_and_the_holder(tmp_path):
    results = tmp_path / "results"
    proc = hold_elsewhere(results)
    try:
        with pytest.raises(PsdError) as e:
            lock_results(results)
        msg = str(e.value)
        assert msg.startswith(f"results folder {results} is in use by another run (pid {proc.pid} on ")
        assert f"in {os.getcwd()}: snakemake -j2 --configfile first.yaml)" in msg and "interleave" in msg
    finally:
        proc.send_signal(signal.SIGKILL)  # as when the machine goes away: the kernel drops the lock
        proc.wait()
    f = lock_results(results)  # no stale lock to clear by hand
    assert json.loads((results / LOCK_NAME).read_text())["pid"] == os.getpid()
    f.close()
    lock_results(results).close()  # and closing releases it


def test_describe_without_details():
    assert describe({}) == "a run that has not said who it is yet"


@pytest.mark.workflow
def test_a_second_snakemake_on_the_same_results_is_refused_and_a_dry_run_is_not(tmp_path):
    results = tmp_path / "results"
    first, second = tmp_path / "first", tmp_path / "second"
    second.mkdir()
    cfg = write_config(second / "c.yaml", {**TINY, "results": str(results)})
    proc = hold_elsewhere(results)
    try:
        t0 = time.perf_counter()
        r = snakemake("-j2", "scenes", "--configfile", str(cfg), workdir=second)
        seconds = time.perf_counter() - t0
        assert r.returncode != 0
        assert f"psdfactory: results folder {results} is in use by another run (pid {proc.pid}" in r.stderr, r.stderr
        assert seconds < 60, seconds  # Snakemake's start-up and DAG on a busy 2-core machine
        assert sorted(p.name for p in results.iterdir()) == [LOCK_NAME]  # nothing written
        assert not (second / ".snakemake" / "locks").exists() or not any((second / ".snakemake" / "locks").iterdir())

        r = snakemake("-n", "scenes", "--configfile", str(cfg), workdir=second)  # a dry run looks only
        assert r.returncode == 0, r.stderr[-2000:]
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()

    first.mkdir()  # a fresh results folder: a dry run does not create it (nor its lock)
    cfg = write_config(first / "c.yaml", {**TINY, "results": str(first / "results")})
    r = snakemake("-n", "scenes", "--configfile", str(cfg), workdir=first)
    assert r.returncode == 0 and not (first / "results").exists(), r.stderr[-2000:]
