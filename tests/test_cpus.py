"""The default thread count honours the affinity mask and the cgroup CPU quota (fake cgroup
trees: the real one here has no quota)."""

from __future__ import annotations

import os

import pytest

from vastray.scene.cpus import available_cpus, cgroup_cpu_quota

AFFINITY = len(os.sched_getaffinity(0))


def fake_cgroup(tmp_path, files: dict[str, str], membership: str = "0::/\n"):
    root = tmp_path / "cgroup"
    root.mkdir(parents=True)
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    proc = tmp_path / "proc-self-cgroup"
    proc.write_text(membership)
    return root, proc


@pytest.mark.parametrize(("cpu_max", "quota"), [
    ("150000 100000\n", 1.5),  # docker --cpus 1.5
    ("100000 100000\n", 1.0),
    ("25000 100000\n", 0.25),
    ("max 100000\n", None),  # no limit
    ("garbage\n", None),  # unreadable: no limit rather than a crash
])
def test_cgroup_v2_quota_is_read_from_cpu_max(tmp_path, cpu_max, quota):
    root, proc = fake_cgroup(tmp_path, {"cpu.max": cpu_max})
    assert cgroup_cpu_quota(root, proc) == quota


def test_the_thread_count_is_the_quota_rounded_up_never_above_the_affinity_nor_below_one(tmp_path):
    for cpu_max, expected in [("150000 100000", min(AFFINITY, 2)), ("25000 100000", 1),
                              ("max 100000", AFFINITY), (f"{100000 * (AFFINITY + 8)} 100000", AFFINITY)]:
        root, proc = fake_cgroup(tmp_path / cpu_max.replace(" ", "-"), {"cpu.max": cpu_max})
        assert available_cpus(root, proc) == expected, cpu_max


def test_no_cgroup_files_means_the_affinity_mask(tmp_path):
    root, proc = fake_cgroup(tmp_path, {})
    assert cgroup_cpu_quota(root, proc) is None
    assert available_cpus(root, proc) == AFFINITY
    assert available_cpus(tmp_path / "absent", tmp_path / "absent-too") == AFFINITY


def test_the_tightest_quota_between_the_root_and_the_process_cgroup_wins(tmp_path):
    # a process on a host (no cgroup namespace): its cgroup is a folder under the mount, and
    # a parent slice may hold the tighter limit
    root, proc = fake_cgroup(tmp_path, {
        "cpu.max": "max 100000",
        "jobs.slice/cpu.max": "300000 100000",
        "jobs.slice/job-7.scope/cpu.max": "500000 100000",
    }, membership="0::/jobs.slice/job-7.scope\n")
    assert cgroup_cpu_quota(root, proc) == 3.0


def test_cgroup_v1_quota_from_cfs_files(tmp_path):
    membership = "4:memory:/\n3:cpu,cpuacct:/docker/abc\n0::/\n"
    root, proc = fake_cgroup(tmp_path, {"cpu,cpuacct/cpu.cfs_quota_us": "200000\n",
                                        "cpu,cpuacct/cpu.cfs_period_us": "100000\n"}, membership)
    assert cgroup_cpu_quota(root, proc) == 2.0
    unlimited, proc = fake_cgroup(tmp_path / "u", {"cpu/cpu.cfs_quota_us": "-1\n",
                                                   "cpu/cpu.cfs_period_us": "100000\n"}, membership)
    assert cgroup_cpu_quota(unlimited, proc) is None


def test_this_machine_gets_at_least_one_thread():
    assert 1 <= available_cpus() <= (os.cpu_count() or 1)
