"""Checks made once before any job runs, so that a misconfiguration fails in seconds with a
message that names what is wrong and how to fix it, instead of hours later (or never) inside a
job: the results folder is writable, and the SLURM profile's account and partitions are set
and known to the cluster. The workflow's main process calls them while it parses the
Snakefile (rules/common.smk); they change nothing, so a dry run runs them too.

Pure functions: the environment, the file access check and the command runner are arguments."""

from __future__ import annotations

import os
import re
import subprocess
from collections.abc import Callable, Mapping
from pathlib import Path

from . import PsdError

ENV_REF = re.compile(r"\$(?:\{([A-Za-z_][A-Za-z0-9_]*)\}|([A-Za-z_][A-Za-z0-9_]*))")

HOW_TO_SET = {
    "PSD_SLURM_ACCOUNT": "your SLURM account, the one sbatch --account takes "
                         "(`sacctmgr -nP show assoc user=$USER format=account` lists yours)",
    "PSD_SLURM_PARTITION": "the partition for the scene jobs (`sinfo -s` lists the partitions)",
    "PSD_SLURM_GPU_PARTITION": "the partition for training, evaluation and the benchmark: one with GPUs "
                               "(`sinfo -s` lists them; a CPU partition works too, slower)",
}


# ---- the results folder ----------------------------------------------------------------------


def results_problem(results: str | os.PathLike, access: Callable[[str, int], bool] = os.access) -> str | None:
    """Why the workflow could not write under `results`, or None. Looks only (no file is
    created): the folder, or where it does not exist yet the nearest folder above it that does,
    must be a folder this user may write into (and not on a read-only filesystem)."""
    path = Path(results).absolute()
    probe = path
    while not probe.exists():
        if probe.is_symlink():
            return f"results folder {path}: {probe} is a broken symbolic link"
        probe = probe.parent
    if not probe.is_dir():
        return f"results folder {path} cannot be created: {probe} is a file, not a folder"
    if not access(str(probe), os.W_OK | os.X_OK):
        where = "it" if probe == path else f"{probe} (where it would be created)"
        return (f"results folder {path} is not writable: {where} does not let this user write, or is on a read-only "
                "filesystem. Set `results:` in the config (or --config results=DIR) to a folder you can write, "
                "or fix its permissions")
    return None


def check_results(results: str | os.PathLike, access: Callable[[str, int], bool] = os.access) -> None:
    problem = results_problem(results, access)
    if problem:
        raise PsdError(problem)


# ---- the SLURM profile -----------------------------------------------------------------------

Resources = Mapping[str, Mapping[str, object]]  # where ("default-resources", "set-resources train") → {key: raw value}


def env_refs(value: object) -> list[str]:
    """The environment variables a raw resource value names ($NAME or ${NAME})."""
    return [a or b for a, b in ENV_REF.findall(value)] if isinstance(value, str) else []


def unset_env_problems(resources: Resources, env: Mapping[str, str]) -> list[str]:
    """One message per environment variable that the profile's resources name but that is not
    set (or empty): Snakemake would pass the literal `$NAME` to sbatch, which hangs or fails
    with a message about the account or partition itself."""
    found: dict[str, list[str]] = {}
    for where, values in resources.items():
        for key, value in values.items():
            for var in env_refs(value):
                if not env.get(var):
                    found.setdefault(var, []).append(f"{where} {key}: {value}")
    return [f"the SLURM profile sets {'; '.join(uses)} — but the environment variable {var} is not set. "
            f"Set it before running Snakemake: export {var}=<name>, {HOW_TO_SET.get(var, 'see slurm/config.yaml')}; "
            "or write the name into the profile instead"
            for var, uses in found.items()]


def expanded(value: object, env: Mapping[str, str]) -> object:
    if not isinstance(value, str):
        return value
    return ENV_REF.sub(lambda m: env.get(m.group(1) or m.group(2), m.group(0)), value)


def slurm_names(resources: Resources, env: Mapping[str, str], key: str) -> dict[str, str]:
    """{name: where it is set} of every `key` (slurm_partition, slurm_account) in the resources."""
    names: dict[str, str] = {}
    for where, values in resources.items():
        if values.get(key) not in (None, ""):
            names.setdefault(str(expanded(values[key], env)), f"{where} {key}")
    return names


def run_command(cmd: list[str], timeout: float = 10.0) -> str | None:
    """A SLURM query's output, or None where it cannot answer (not installed, no controller,
    no accounting database, too slow)."""
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return r.stdout if r.returncode == 0 else None


def unknown_name_problems(resources: Resources, env: Mapping[str, str], user: str,
                          run: Callable[[list[str]], str | None] = run_command) -> list[str]:
    """Partitions and accounts the profile names that the cluster does not know, asked of
    `sinfo` and `sacctmgr` where they answer (skipped where they do not: not a cluster, no
    accounting database)."""
    problems = []
    partitions = slurm_names(resources, env, "slurm_partition")
    if partitions:
        out = run(["sinfo", "-h", "-o", "%R"])
        known = {line.strip() for line in out.splitlines() if line.strip()} if out else set()
        for name, where in partitions.items():
            if known and name not in known:
                problems.append(f"SLURM partition {name!r} ({where}) does not exist on this cluster; sinfo lists: "
                                f"{', '.join(sorted(known))}. Set the PSD_SLURM_*PARTITION variables (or the profile) "
                                "to one of these")
    accounts = slurm_names(resources, env, "slurm_account")
    if accounts:
        out = run(["sacctmgr", "-nP", "show", "assoc", f"where user={user}", "format=account"])
        known = {line.strip() for line in out.splitlines() if line.strip()} if out else set()
        for name, where in accounts.items():
            if known and name not in known:
                problems.append(f"SLURM account {name!r} ({where}) is not one of {user}'s accounts; sacctmgr lists: "
                                f"{', '.join(sorted(known))}. Set PSD_SLURM_ACCOUNT (or the profile) to one of these")
    return problems


def check_slurm(resources: Resources, env: Mapping[str, str], user: str,
                run: Callable[[list[str]], str | None] = run_command) -> None:
    """Refuse a SLURM run whose profile names unset environment variables, or partitions and
    accounts the cluster does not know; the unset variables are reported first (no query is
    made with a literal `$NAME`)."""
    problems = unset_env_problems(resources, env)
    if not problems:
        problems = unknown_name_problems(resources, env, user, run)
    if problems:
        raise PsdError("\n".join(problems))


