"""The default thread count honours the affinity mask and the cgroup CPU quota (fake cgroup
trees: the real one here has no quota)."""

from __future__ import annotations

import os

import pytest

from vastray.scene.cpus import CpuClock, available_cpus, cgroup_cpu_quota, cgroup_cpu_throttled_s

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


# -- what a quota held a process back ---------------------------------------------------------
def test_held_seconds_are_read_from_cpu_stat_v2_and_v1(tmp_path):
    root, proc = fake_cgroup(tmp_path / "v2", {
        "cpu.stat": "usage_usec 900000\nnr_periods 120\nnr_throttled 40\nthrottled_usec 1500000\n"})
    assert cgroup_cpu_throttled_s(root, proc) == pytest.approx(1.5)
    membership = "3:cpu,cpuacct:/docker/abc\n0::/\n"
    root, proc = fake_cgroup(tmp_path / "v1", {
        "cpu,cpuacct/cpu.stat": "nr_periods 120\nnr_throttled 52\nthrottled_time 2580000000\n"},
        membership)
    assert cgroup_cpu_throttled_s(root, proc) == pytest.approx(2.58)
    root, proc = fake_cgroup(tmp_path / "none", {"cpu.stat": "usage_usec 5\n"})
    assert cgroup_cpu_throttled_s(root, proc) is None  # no throttling counter: unknown, not 0


def test_the_cpu_clock_reports_held_seconds_only_under_a_quota(tmp_path):
    root, proc = fake_cgroup(tmp_path / "q", {"cpu.max": "25000 100000\n",
                                              "cpu.stat": "throttled_usec 1000000\n"})
    clock = CpuClock(root, proc)
    assert clock.quota == 0.25
    mark = clock.mark()
    (root / "cpu.stat").write_text("throttled_usec 1750000\n")
    spent = clock.since(mark)
    assert spent["cpu_throttled_s"] == pytest.approx(0.75) and spent["busy_cpu_s"] >= 0.0
    root, proc = fake_cgroup(tmp_path / "free", {"cpu.max": "max 100000\n",
                                                 "cpu.stat": "throttled_usec 1000000\n"})
    assert set(CpuClock(root, proc).since(CpuClock(root, proc).mark())) == {"busy_cpu_s",
                                                                          "page_faults"}


def test_the_cpu_clock_counts_the_pages_a_span_touches_first():
    import mmap

    import numpy as np

    clock = CpuClock()
    mark = clock.mark()
    mapping = mmap.mmap(-1, 8 << 20)  # 2,048 pages never touched
    pages = np.frombuffer(mapping, np.uint8)
    pages[::mmap.PAGESIZE] = 1
    faults = clock.since(mark)["page_faults"]
    del pages
    mapping.close()
    assert faults >= (8 << 20) // mmap.PAGESIZE
    assert clock.since(clock.mark())["page_faults"] < 1000  # nothing touched in between


def test_a_node_says_when_its_quota_is_below_a_core(caplog):
    from vastray.actors.node import warn_of_a_quota_below_a_core

    with caplog.at_level("WARNING", logger="vastray"):
        warn_of_a_quota_below_a_core(1.0)
        warn_of_a_quota_below_a_core(2.0)
        assert not caplog.records
        warn_of_a_quota_below_a_core(0.25)
    assert len(caplog.records) == 1 and "0.25 CPU" in caplog.records[0].getMessage()


def test_the_cli_says_when_a_quota_held_the_nodes_back():
    from vastray.actors.results import quota_lines

    per_node = [{"rank": 0, "counters": {"cpu_throttled_s": 0.4}},
                {"rank": 1, "counters": {"cpu_throttled_s": 2.58}}]
    lines = quota_lines({"cpu_throttled_s_max": 2.58, "per_node": per_node}, {"busy_max": 6.9})
    assert len(lines) == 1 and "2.58 s of throttled time (node 1" in lines[0] and "6.90 s" in lines[0]
    # a hold under 5 % of the busiest node's time, or no quota at all: nothing said
    assert quota_lines({"cpu_throttled_s_max": 0.3, "per_node": per_node}, {"busy_max": 6.9}) == []
    assert quota_lines({"per_node": []}, {"busy_max": 6.9}) == []
