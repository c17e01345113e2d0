"""Running Snakemake on the repository's workflow from a test: each test run gets its own
working directory (so its .snakemake metadata and locks are its own, and none is left in the
repository)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]


def snakemake(*args: str, workdir: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("snakemake")
    cmd = [str(exe), "-s", str(REPO / "Snakefile"), "-d", str(workdir)]
    return subprocess.run(cmd + list(args), cwd=workdir, capture_output=True, text=True, env=env)


def own_copy(work: Path, dest: Path) -> Path:
    """A copy of a built working directory (results, .snakemake metadata, modification times) for
    a test that changes it, so that the tests sharing the original stay independent of order.
    The configs give the results root relative to the working directory, so the copy is whole."""
    shutil.copytree(work, dest, symlinks=True)
    return dest


def write_config(path: Path, cfg: dict) -> Path:
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def planned_jobs(result: subprocess.CompletedProcess) -> Counter:
    """Jobs per rule from a dry run's 'Job stats' table (empty when there is nothing to do)."""
    out = result.stdout + result.stderr
    counts: Counter = Counter()
    if "Job stats:" not in out:
        return counts
    table = out.split("Job stats:", 1)[1]
    for line in table.splitlines()[3:]:
        m = re.match(r"^(\S+)\s+(\d+)$", line.strip())
        if not m:
            break
        if m.group(1) != "total":
            counts[m.group(1)] = int(m.group(2))
    return counts


def planned_wildcards(result: subprocess.CompletedProcess, rule: str) -> list[str]:
    """The wildcards line of every planned job of `rule` in a dry run."""
    out = (result.stdout + result.stderr).splitlines()
    found, current = [], None
    for line in out:
        s = line.strip()
        if s.startswith("rule ") and s.endswith(":"):
            current = s[5:-1]
        elif s.startswith("localrule ") and s.endswith(":"):
            current = s[10:-1]
        elif s.startswith("wildcards:") and current == rule:
            found.append(s[len("wildcards:"):].strip())
        elif not s:
            current = None
    return found
