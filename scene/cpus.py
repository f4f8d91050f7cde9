"""The CPUs this process may use: the default for every ``threads`` setting.

``os.cpu_count()`` counts the machine's cores, whatever the process is allowed: a container
started with ``docker run --cpus 2`` (or compose's ``cpus:``, or a Kubernetes CPU limit) sees
every host core, so N such containers each starting one thread per host core oversubscribe
the host N times over and are throttled by their quota. The count here is the affinity mask
(``taskset``, ``--cpuset-cpus``, Slurm's binding) lowered to the cgroup CPU quota, rounded up
(a quota of 1.5 CPUs gives 2 threads, as Go and the JVM round it).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

CGROUP_ROOT = Path("/sys/fs/cgroup")
PROC_CGROUP = Path("/proc/self/cgroup")


def available_cpus(cgroup_root: str | os.PathLike = CGROUP_ROOT,
                   proc_cgroup: str | os.PathLike = PROC_CGROUP) -> int:
    """Threads worth running on: the CPUs in this process's affinity mask, at most the cgroup
    CPU quota rounded up, and at least 1.

    Parameters
    ----------
    cgroup_root : where the cgroup file system is mounted (a fake tree in tests).
    proc_cgroup : this process's cgroup membership file (``/proc/self/cgroup``).
    """
    try:
        count = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        count = os.cpu_count() or 1
    quota = cgroup_cpu_quota(cgroup_root, proc_cgroup)
    if quota is not None:
        count = min(count, math.ceil(quota))
    return max(1, count)


def cgroup_cpu_quota(cgroup_root: str | os.PathLike = CGROUP_ROOT,
                     proc_cgroup: str | os.PathLike = PROC_CGROUP) -> float | None:
    """The tightest CPU quota (in CPUs) over this process's cgroup and its ancestors, cgroup v2
    (``cpu.max``) or v1 (``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``); None when unlimited or
    unreadable.

    A container usually sees its own cgroup at the mount's root; a process on a host (or in a
    container sharing the host's cgroup namespace) sees it at the path ``/proc/self/cgroup``
    names, so both, and every folder between them, are read.
    """
    root = Path(cgroup_root)
    paths = _membership(Path(proc_cgroup))
    quotas = [q for folder in _folders(root, paths.get("", "/")) if (q := _v2_quota(folder))]
    for mount in ("cpu", "cpu,cpuacct", "cpuacct,cpu"):
        for folder in _folders(root / mount, paths.get("cpu", "/")):
            if q := _v1_quota(folder):
                quotas.append(q)
    return min(quotas) if quotas else None


def _membership(proc_cgroup: Path) -> dict[str, str]:
    """``/proc/self/cgroup`` as {controller: path}: ``""`` for the v2 hierarchy, ``"cpu"`` for
    the v1 hierarchy holding the cpu controller."""
    try:
        lines = proc_cgroup.read_text().splitlines()
    except OSError:
        return {}
    paths = {}
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        controllers = parts[1].split(",")
        if parts[1] == "":
            paths[""] = parts[2]
        elif "cpu" in controllers:
            paths["cpu"] = parts[2]
    return paths


def _folders(mount: Path, path: str) -> list[Path]:
    """The mount's root and each folder from it down to ``mount/path``, where they exist."""
    folders, folder = [mount], mount
    for part in Path(path).parts[1:]:
        folder = folder / part
        if not folder.is_dir():
            break
        folders.append(folder)
    return folders


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except (OSError, UnicodeDecodeError):
        return None


def _v2_quota(folder: Path) -> float | None:
    text = _read(folder / "cpu.max")  # "QUOTA PERIOD" in microseconds, or "max PERIOD"
    if text is None:
        return None
    fields = text.split()
    try:
        return _ratio(fields[0], fields[1]) if len(fields) == 2 and fields[0] != "max" else None
    except ValueError:
        return None


def _v1_quota(folder: Path) -> float | None:
    quota, period = _read(folder / "cpu.cfs_quota_us"), _read(folder / "cpu.cfs_period_us")
    if quota is None or period is None:
        return None
    try:
        return _ratio(quota, period)  # quota -1: unlimited
    except ValueError:
        return None


def _ratio(quota: str, period: str) -> float | None:
    q, p = int(quota), int(period)
    return q / p if q > 0 and p > 0 else None
