"""Test-only (tests/sigkill.py puts this folder first on the PYTHONPATH of the commands it runs;
Python imports `sitecustomize` at start-up). Never on the package's path, and inert unless one
of these is set:

- PSD_TEST_KILL_AT_REPLACE=N: the process kills itself with SIGKILL at its N-th `os.replace`,
  before renaming — the moment io.atomic_path moves a finished temporary file into place: the
  file is whole, its final name absent, and nothing gets to clean up.
- PSD_TEST_RECORD_REPLACES=FILE: every `os.replace` appends its destination to FILE.
"""

import os
import signal

_KILL_AT = int(os.environ.get("PSD_TEST_KILL_AT_REPLACE") or 0)
_RECORD = os.environ.get("PSD_TEST_RECORD_REPLACES")

if _KILL_AT or _RECORD:
    _real_replace = os.replace
    _calls = [0]

    def _replace(src, dst, *args, **kwargs):
        _calls[0] += 1
        if _RECORD:
            with open(_RECORD, "a") as f:
                f.write(os.path.abspath(os.fspath(dst)) + "\n")
        if _calls[0] == _KILL_AT:
            os.kill(os.getpid(), signal.SIGKILL)
        return _real_replace(src, dst, *args, **kwargs)

    os.replace = _replace
