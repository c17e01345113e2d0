"""One run per results folder.

Snakemake locks its working directory (`.snakemake/`), not the outputs: two runs started from
different directories with the same `results:` would both write there, interleaved. The
workflow's main process takes an exclusive `flock` on `<results>/.psdfactory.lock` as it starts
running jobs (Snakemake's `onstart`: not in a dry run, not in the jobs it starts) and holds it
until it exits. The kernel releases the lock when the process dies however it dies (`kill -9`
included), so no stale lock is ever left to clear by hand; the file stays, naming its last
holder, and is taken over by the next run.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import sys
import time
from pathlib import Path
from typing import IO

from . import PsdError

LOCK_NAME = ".psdfactory.lock"


def holder(argv: list[str] | None = None) -> dict:
    """Who holds the lock, written into the lock file for a refused run to quote."""
    return {"pid": os.getpid(), "host": socket.gethostname(), "cwd": os.getcwd(),
            "started": time.strftime("%Y-%m-%d %H:%M:%S"), "command": " ".join(sys.argv if argv is None else argv)}


def describe(info: dict) -> str:
    """The other run, in words: 'pid 4242 on node1, started 2025-01-01 10:00:00 in /work/a: snakemake -j2'."""
    if not info:
        return "a run that has not said who it is yet"
    return (f"pid {info.get('pid', '?')} on {info.get('host', '?')}, started {info.get('started', '?')} in "
            f"{info.get('cwd', '?')}: {info.get('command', '?')}")


def read_holder(text: str) -> dict:
    try:
        info = json.loads(text)
    except ValueError:
        return {}
    return info if isinstance(info, dict) else {}


def lock_results(results: str | os.PathLike, info: dict | None = None) -> IO[str]:
    """Take the results folder's lock for this process, or raise a PsdError naming the run that
    holds it. Keep the returned file open as long as the run goes on (closing it, or the
    process ending, releases the lock)."""
    folder = Path(results).absolute()
    folder.mkdir(parents=True, exist_ok=True)
    f = open(folder / LOCK_NAME, "a+")  # held open for the life of the run
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.seek(0)
        other = read_holder(f.read())
        f.close()
        raise PsdError(
            f"results folder {folder} is in use by another run ({describe(other)}); two runs writing one results "
            f"folder would interleave their files. Wait for that run to end (or stop it), or give this one another "
            f"`results:` (--config results=DIR). The lock is {folder / LOCK_NAME}; it goes with its process, so a "
            "run that was killed holds none") from None
    f.seek(0)
    f.truncate()
    f.write(json.dumps(info or holder()) + "\n")
    f.flush()
    return f
