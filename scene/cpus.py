"""The CPUs this process may use: the default for every ``threads`` setting, and Embree's
build threads (``scene.embree.library.device_config``).

``os.cpu_count()`` counts the machine's cores, whatever the process is allowed: a container
started with ``docker run --cpus 2`` (or compose's ``cpus:``, or a Kubernetes CPU limit) sees
every host core, so N such containers each starting one thread per host core oversubscribe
the host N times over and are throttled by their quota. The count here is the affinity mask
(``taskset``, ``--cpuset-cpus``, Slurm's binding) lowered to the cgroup CPU quota, rounded up
(a quota of 1.5 CPUs gives 2 threads, as Go and the JVM round it).

A quota also holds a process back: once its threads together have used ``quota x period``
CPU seconds in a period (100 ms by default), none of them runs until the period ends.
``cgroup_cpu_throttled_s`` reads how long the kernel held it so (``cpu.stat``), and
``CpuClock`` gives a render's CPU seconds and those held seconds over a span, which every
node reports (``busy_cpu_s``, ``cpu_throttled_s``), and the span's minor page faults
(``page_faults``: pages of memory touched for the first time, which a fresh node pays for in
every job; ``vastray.sim.first_touch``).
"""

from __future__ import annotations

import math
import os
import resource
import time
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
    v2, v1 = _cpu_cgroups(cgroup_root, proc_cgroup)
    quotas = [q for folder in v2 if (q := _v2_quota(folder))]
    quotas += [q for folder in v1 if (q := _v1_quota(folder))]
    return min(quotas) if quotas else None


def cgroup_cpu_throttled_s(cgroup_root: str | os.PathLike = CGROUP_ROOT,
                           proc_cgroup: str | os.PathLike = PROC_CGROUP) -> float | None:
    """Seconds the kernel has throttled this process's cgroup (or an ancestor's) for its CPU
    quota, the most over the cgroups from the mount's root down to the process's: cgroup v2
    ``cpu.stat`` ``throttled_usec``, v1 ``cpu.stat`` ``throttled_time`` (nanoseconds); None
    where none is readable. A counter since the cgroup was made: take differences. The
    kernel adds the time each core's queue of the group was held, so a group held on two
    cores for a second counts about 2 s: more than the wall time where the group's threads
    wanted several cores. It counts the whole group: every process in it."""
    v2, v1 = _cpu_cgroups(cgroup_root, proc_cgroup)
    held = [seconds for folder in v2
            if (seconds := _stat_seconds(folder, "throttled_usec", 1e-6)) is not None]
    held += [seconds for folder in v1
             if (seconds := _stat_seconds(folder, "throttled_time", 1e-9)) is not None]
    return max(held) if held else None


def _cpu_cgroups(cgroup_root: str | os.PathLike,
                 proc_cgroup: str | os.PathLike) -> tuple[list[Path], list[Path]]:
    """The cgroup folders over this process that may hold its CPU settings: (the v2
    hierarchy's, the v1 cpu controller's), each from the mount's root down to the
    process's cgroup (see ``cgroup_cpu_quota``)."""
    root = Path(cgroup_root)
    paths = _membership(Path(proc_cgroup))
    v1 = [folder for mount in ("cpu", "cpu,cpuacct", "cpuacct,cpu")
          for folder in _folders(root / mount, paths.get("cpu", "/"))]
    return _folders(root, paths.get("", "/")), v1


class CpuClock:
    """This process's CPU seconds (all its threads) and, where a cgroup CPU quota holds it,
    the seconds its quota held it back, between a ``mark`` and now.

    Parameters
    ----------
    cgroup_root, proc_cgroup : as for ``cgroup_cpu_quota`` (fake trees in tests).
    """

    def __init__(self, cgroup_root: str | os.PathLike = CGROUP_ROOT,
                 proc_cgroup: str | os.PathLike = PROC_CGROUP):
        self._where = (cgroup_root, proc_cgroup)
        #: the tightest quota in CPUs (None: no quota, and nothing to read for held seconds)
        self.quota = cgroup_cpu_quota(*self._where)

    def mark(self) -> tuple[float, float | None, int]:
        """Now: (CPU seconds, held seconds or None, minor page faults)."""
        held = cgroup_cpu_throttled_s(*self._where) if self.quota is not None else None
        return time.process_time(), held, resource.getrusage(resource.RUSAGE_SELF).ru_minflt

    def since(self, mark: tuple[float, float | None, int]) -> dict[str, float]:
        """What was spent since ``mark``: ``busy_cpu_s``, ``page_faults``, and
        ``cpu_throttled_s`` where a quota holds the process and its counter is readable."""
        cpu, held, faults = self.mark()
        spent = {"busy_cpu_s": cpu - mark[0], "page_faults": faults - mark[2]}
        if held is not None and mark[1] is not None:
            spent["cpu_throttled_s"] = round(max(held - mark[1], 0.0), 4)
        return spent


def _stat_seconds(folder: Path, key: str, unit_s: float) -> float | None:
    """``key`` of ``folder/cpu.stat`` in seconds (its value times ``unit_s``), or None."""
    text = _read(folder / "cpu.stat")
    if text is None:
        return None
    for line in text.splitlines():
        fields = line.split()
        if len(fields) == 2 and fields[0] == key:
            try:
                return int(fields[1]) * unit_s
            except ValueError:
                return None
    return None


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
