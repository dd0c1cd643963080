"""What every benchmark record carries about the run: machine, versions, date, load.

Not a benchmark (``polygeo bench`` lists only ``bm_*.py``): ``environment()`` at the start of
a run and ``finish(env)`` at its end give the ``machine`` / ``versions`` / ``date_utc`` /
load-average fields of a record, so that a chart read months later says where and when it
was measured.
Benchmarks import it as ``from run_env import environment`` after putting their own folder on
``sys.path`` (``polygeo bench`` runs a script with :func:`runpy.run_path`, which does not).
"""

from __future__ import annotations

import os
import platform
import sys
import time
from importlib.metadata import PackageNotFoundError, version

#: Distributions whose versions every record lists (absent ones are recorded as absent).
PACKAGES = ("polygeo", "numpy", "scipy", "torch", "numba", "trimesh", "matplotlib")


def _load() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except (OSError, AttributeError):  # not on every platform
        return None


def environment(packages: tuple[str, ...] = ()) -> dict:
    """Machine, versions, start date (UTC) and load average at the start of a run.

    Parameters
    ----------
    packages : tuple of str
        Distributions to record besides :data:`PACKAGES` (a benchmark's peers).

    Returns
    -------
    dict
        ``{"machine": {...}, "versions": {...}, "date_utc": str, "loadavg_start": [1, 5, 15
        minute averages] or None}``; JSON-able.
    """
    versions = {}
    for name in (*PACKAGES, *packages):
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            versions[name] = None
    return {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(),
            "python": sys.version.split()[0],
        },
        "versions": versions,
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "loadavg_start": _load(),
        "note": "a shared machine: wall times include waiting for a core; CPU seconds do not",
    }


def finish(env: dict) -> dict:
    """``env`` with the end date and the load average at the end of the run added."""
    return {**env, "date_end_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "loadavg_end": _load()}
