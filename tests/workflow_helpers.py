"""Running Snakemake on the repository's workflow from a test: each test run gets its own
working directory (so its .snakemake metadata and locks are its own)."""

from __future__ import annotations

import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]


def snakemake(*args: str, workdir: Path | None = None, env: dict | None = None) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("snakemake")
    cmd = [str(exe), "-s", str(REPO / "Snakefile")]
    if workdir is not None:
        cmd += ["-d", str(workdir)]
    return subprocess.run(cmd + list(args), cwd=workdir or REPO, capture_output=True, text=True, env=env)


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
