"""``vastray calibrate`` (``vastray.sim.calibrate``): the cost model measured with the real
components on this machine, its fits, its peer process and its calibration file."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import asdict, fields

import numpy as np
import pytest

from vastray.commands_sim import check_output_file
from vastray.scene.errors import InputError
from vastray.scene.generate import generate
from vastray.scene.store import Store
from vastray.sim import calibrate as cal
from vastray.sim.costs import VERSION, CostModel
from vastray.sim.node_cost import SETUP_NODES, span_per_setup
from vastray.sim.warmup import WarmProcesses, beside_others, interpolated, throughput_of

CONSTANTS = ("trace_ray_s", "shade_ray_s", "shadow_ray_s", "activation_s",
             "shadow_activation_s", "camera_ray_s", "load_byte_s", "build_triangle_s",
             "latency_s", "byte_s", "receive_s", "warmup_s", "offload_s")
# differences of a real render and its simulation, clamped at 0: a node whose simulation
# already charges all it does measures 0 (the quick calibration gave warmup_s 0 in two of
# three runs, session 34)
SET_UP_COSTS = ("warmup_s", "node_setup_s", "tile_setup_s", "insitu_setup_s")
VASTRAY = [sys.executable, "-m", "vastray"]  # __main__ without a main guard: spawn must cope


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("calibrate") / "rm.store"
    generate("rm", path, 32, grid=(2, 2, 1))
    return path


@pytest.fixture(scope="module")
def quick(store):
    """One quick calibration of ``store``: (model, [(fraction, text), ...], seconds)."""
    steps = []
    start = time.perf_counter()
    model = cal.calibrate(store, quick=True, progress=lambda f, t: steps.append((f, t)))
    return model, steps, time.perf_counter() - start


# -- a real calibration ---------------------------------------------------------------------
@pytest.mark.slow  # the quick calibration takes 75 s; .ci/run runs it
def test_quick_calibration_measures_every_constant_plausibly(quick):
    model, _, _seconds = quick
    values = {name: getattr(model, name) for name in CONSTANTS if name not in SET_UP_COSTS}
    assert all(math.isfinite(v) and v > 0 for v in values.values()), values
    # a set-up costs nothing up to a fraction of a second (a 1-node render of the store
    # takes about 0.2 s)
    set_up = {name: getattr(model, name) for name in SET_UP_COSTS}
    assert all(0.0 <= v < 0.5 for v in set_up.values()), set_up
    assert 1e-6 < model.latency_s < 0.1
    assert 1e-12 < model.byte_s < 1e-6  # between 1 MB/s and 1 TB/s
    assert model.load_byte_s < 1e-6 and model.build_triangle_s < 1e-4
    # what a read and a build cost besides their bytes and triangles: none (the store's
    # domains too alike to tell) up to a few milliseconds
    assert 0.0 <= model.read_fixed_s < 5e-3 and 0.0 <= model.build_fixed_s < 5e-3
    assert model.trace_ray_s < 1e-3 and model.shade_ray_s < 1e-3
    # a domain's activation costs more than one of its queries; a camera ray is made in
    # vectorised numpy, far cheaper than tracing and shading one
    assert model.activation_s > model.trace_ray_s + model.shade_ray_s
    assert model.camera_ray_s < model.trace_ray_s + model.shade_ray_s
    # a thread hand-off costs microseconds to a few milliseconds, not a whole activation's
    # worth of seconds; simulating here charges traces their CPU time
    assert 1e-6 < model.offload_s < 5e-3
    # a batch through the nodes' management actors costs more CPU than the raw wire's one
    # way, but not a whole activation's worth
    assert 1e-6 < model.receive_s < 5e-3
    assert model.trace_scale == 1.0 and model.decision_scale == 1.0 and model.load_scale == 1.0
    # a page's first touch costs 0.1-10 us; a path touches a fraction of a page up to a few
    assert 1e-8 < model.page_fault_s < 1e-4 and 0.0 < model.fresh_pages_per_path < 8.0
    # the throughput with 1 .. 4 x cores busy processes (a validation runs 8 nodes on 2 cores):
    # one process is the unit, and k processes give at most what k processes and the cores can
    assert len(model.throughput) == 4 * model.cores and model.throughput[0] == 1.0
    assert all(0.0 < t <= min(k, model.cores)
               for k, t in enumerate(model.throughput, start=1)), model.throughput
    # (its time, about 75 s on a quiet machine, is no test's business)


@pytest.mark.slow  # the quick calibration takes 75 s; .ci/run runs it
def test_quick_calibration_records_the_machine_and_reports_progress(quick, store):
    model, steps, _ = quick
    assert model.cores == len(os.sched_getaffinity(0))
    machine = model.machine
    assert {"hostname", "cpu", "platform", "python", "vastray", "date"} <= set(machine)
    assert machine["python"] == sys.version.split()[0]
    assert machine["calibration"]["store"] == str(store) and machine["calibration"]["quick"]
    fractions = [f for f, _ in steps]
    assert fractions == sorted(fractions) and 0 <= fractions[0] and fractions[-1] == 1.0
    assert any("ray batches" in text for _, text in steps)


@pytest.mark.slow  # the quick calibration takes 75 s; .ci/run runs it
def test_calibration_file_round_trips(quick, tmp_path):
    model, _, _ = quick
    model.save(tmp_path / "costs.json")
    assert asdict(CostModel.load(tmp_path / "costs.json")) == asdict(model)
    assert not list(tmp_path.glob("*.partial"))


# -- the command ----------------------------------------------------------------------------
def test_the_table_names_every_constant_the_model_charges_by(tmp_path):
    from vastray.commands_sim import costs_table

    table = costs_table(CostModel(cores=2), tmp_path / "costs.json", 1.0)
    printed = {line.split()[0] for line in table.splitlines() if line.startswith("  ")}
    assert {f.name for f in fields(CostModel)} - {"cores", "throughput", "machine",
                                                  "others"} <= printed


@pytest.mark.slow  # a second whole calibration (75 s alone); .ci/run runs it
def test_cli_writes_the_file_and_prints_the_table(store, tmp_path):
    out = tmp_path / "costs.json"
    # a generous bound: beside the other calibration on 2 cores it took over 120 s
    proc = subprocess.run([*VASTRAY, "calibrate", str(store), "-o", str(out), "--quick"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    # every constant and scale the model charges by, each on a line of its own (``others``
    # is no constant of the machine: the other processes beside one run, 0 from a calibration)
    printed = {line.split()[0] for line in proc.stdout.splitlines() if line.startswith("  ")}
    assert {f.name for f in fields(CostModel)} - {"cores", "throughput", "machine",
                                                  "others"} <= printed
    assert f"written to {out}" in proc.stdout
    model = CostModel.load(out)
    assert model.latency_s > 0 and model.machine["calibration"]["quick"]
    assert json.loads(out.read_text())["version"] == VERSION


def test_the_machine_probe_measures_again_only_what_moves(store):
    # receive_s, offload_s and the throughput of busy processes measured now, every other
    # constant kept; a second probe measures again (its own numbers, not a copy of the first)
    # and adds a round of side-by-side renders to the throughput's
    base = CostModel(latency_s=1e-4, trace_ray_s=3e-6, cores=2, throughput=(1.0, 1.5))
    probe = cal.MachineProbe(store, cores=2, beyond_cores=False)
    try:
        assert len(probe.rounds) == len(probe.messages) == probe.SEED_ROUNDS
        first, second = probe.now(base), probe.now(base)
        assert len(probe.rounds) == probe.SEED_ROUNDS + 2
        # the message cost charged is the median of the measurements so far, not the latest
        assert len(probe.messages) == len(probe.offloads) == probe.SEED_ROUNDS + 2
        assert second.receive_s == pytest.approx(
            max(0.0, float(np.median(probe.messages)) - base.latency_s))
        assert second.offload_s == pytest.approx(float(np.median(probe.offloads)))
        assert all(set(r) == {1, 2} and len(r[2]) == 2 for r in probe.rounds)
        # as measured, read beside the busy processes of others seen as the rounds began
        assert len(probe.others) == probe.SEED_ROUNDS + 1
        assert second.throughput[1] == pytest.approx(beside_others(
            interpolated(throughput_of(probe.rounds, 2)), float(np.median(probe.others)), 2)[1])
    finally:
        probe.close()
    # its warm processes are gone with it
    assert all(p.poll() is not None for p in probe.processes.processes)
    for now in (first, second):
        assert 0 < now.receive_s < 0.05 and 0 < now.offload_s < 0.05
        # 1 and 2 processes measured, at most what the cores give; 3 .. 8 run 2 at a time,
        # as fast as 2 where the calibration (base) measured no more processes than cores
        # (read at the count in all beside others' processes, as the suite's other workers:
        # never faster with more, the last counts as 2 measured)
        assert len(now.throughput) == 8 and now.throughput[0] == 1.0
        assert 0 < now.throughput[1] <= 2.0
        assert all(a >= b - 1e-12 for a, b in zip(now.throughput[1:], now.throughput[2:],
                                                  strict=False))
        assert now.throughput[-1] == pytest.approx(now.throughput[-2])
        assert asdict(now) == asdict(base) | {"receive_s": now.receive_s,
                                              "offload_s": now.offload_s,
                                              "throughput": now.throughput}
    assert (first.receive_s, first.offload_s) != (second.receive_s, second.offload_s)


def test_the_probe_measures_busy_processes_beyond_the_cores_by_default(store):
    # 8 processes on 2 cores measured round after round, not the calibration's ratio kept:
    # one quick calibration's 3 rounds put it anywhere between 0.65 and 1.00 of 2 processes
    calibrated = CostModel(cores=2, throughput=(1.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0))
    probe = cal.MachineProbe(store, cores=2)
    try:
        assert probe.counts == [1, 2, 4, 8] and len(probe.processes.processes) == 8
        now = probe.now(calibrated)
        assert all(set(r) == {1, 2, 4, 8} and len(r[8]) == 8 for r in probe.rounds)
        assert now.throughput == pytest.approx(beside_others(
            interpolated(throughput_of(probe.rounds, 2)), float(np.median(probe.others)), 2))
        assert len(now.throughput) == 8 and all(0 < t <= 2.0 for t in now.throughput[1:])
    finally:
        probe.close()


def test_a_throughput_measured_beside_others_is_read_at_the_count_in_all():
    """Measured beside one busy process, k processes ran among k + 1: the simulator, which
    runs that process beside its nodes again, reads the efficiency of k at k + 1."""
    measured = (1.0, 1.8, 1.65, 1.5)
    assert beside_others(measured, 1.0, 2) == pytest.approx((1.0, 2.0, 1.8, 1.65))
    # half a process: between the counts
    assert beside_others(measured, 0.5, 2)[2] == pytest.approx(2 * (0.9 + 0.825) / 2)
    assert beside_others(measured, 0.0, 2) == measured  # quiet: as measured
    # two beside: 3 in all is one measured process (a core each): efficiency 1
    assert beside_others(measured, 2.0, 2)[:3] == pytest.approx((1.0, 2.0, 2.0))


def test_beyond_the_cores_the_probe_keeps_the_calibration_s_slow_down():
    # the calibration: 4 processes on 2 cores at 0.9 of 2 (switching costs each CPU)
    assert cal.oversubscribed((1.0, 1.6), (1.0, 2.0, 1.9, 1.8), 4) == pytest.approx(
        (1.0, 1.6, 1.6 * 0.95, 1.6 * 0.9))
    # no calibrated count beyond the cores, or a ratio above 1 (noise): as fast as at them
    assert cal.oversubscribed((1.0, 1.6), (1.0, 2.0), 4) == (1.0, 1.6, 1.6, 1.6)
    assert cal.oversubscribed((1.0, 1.6), (1.0, 1.5, 1.7, 1.8), 4) == (1.0, 1.6, 1.6, 1.6)
    # measured beyond the cores already (the probe's default): as measured
    assert cal.oversubscribed((1.0, 2.0, 1.9, 1.5), (1.0, 2.0, 2.0, 2.0), 4) == (
        1.0, 2.0, 1.9, 1.5)


def test_a_set_up_per_node_is_its_share_of_the_span_of_nodes_sharing_the_cores():
    assert SETUP_NODES > 2  # measured where nodes share the cores, as the validation's do
    throughput = (1.0, 2.0, 1.9, 1.8, 1.75, 1.7, 1.68, 1.65)
    # each node on a core of its own: one set-up adds its own length to the span
    assert span_per_setup(CostModel(cores=None, throughput=throughput), 8) == 1.0
    assert span_per_setup(CostModel(cores=2, throughput=throughput), 2) == 1.0
    # 8 nodes on 2 cores: 8 set-ups at the throughput of 8 busy processes
    assert span_per_setup(CostModel(cores=2, throughput=throughput), 8) == pytest.approx(
        8 / 1.65)
    # no throughput measured that far: the cores' worth
    assert span_per_setup(CostModel(cores=2, throughput=(1.0, 2.0)), 8) == 4.0


def test_a_measuring_process_that_fails_is_named_with_its_error(tmp_path):
    missing = tmp_path / "missing.store"
    with pytest.raises(RuntimeError, match="did not get ready: .*missing.store"):
        WarmProcesses(str(missing), True, 2)


def test_a_measuring_process_that_cannot_start_leaves_none_running(tmp_path, monkeypatch):
    import subprocess

    import vastray.sim.warmup as warmup

    started, real_popen = [], subprocess.Popen

    def popen(*args, **kwargs):
        if started:
            raise OSError("no more processes")
        started.append(real_popen(*args, **kwargs))
        return started[-1]

    monkeypatch.setattr(warmup.subprocess, "Popen", popen)
    with pytest.raises(OSError, match="no more processes"):
        WarmProcesses(str(tmp_path / "missing.store"), True, 2)
    assert len(started) == 1 and started[0].poll() is not None


def test_cli_names_a_missing_store_and_writes_nothing(tmp_path):
    missing, out = tmp_path / "nowhere.store", tmp_path / "costs.json"
    proc = subprocess.run([*VASTRAY, "calibrate", str(missing), "-o", str(out), "--quick"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0
    assert str(missing) in proc.stderr and "Traceback" not in proc.stderr
    assert not out.exists()


def test_an_output_that_cannot_be_written_is_named_before_any_measuring(tmp_path):
    with pytest.raises(InputError, match="does not exist") as err:
        check_output_file(str(tmp_path / "no" / "costs.json"))
    assert str(tmp_path / "no" / "costs.json") in str(err.value)
    with pytest.raises(InputError, match="is a folder"):
        check_output_file(str(tmp_path))
    assert check_output_file(str(tmp_path / "costs.json")) == tmp_path / "costs.json"


# -- bad calibration files ------------------------------------------------------------------
@pytest.mark.parametrize("text, problem", [
    ("{not json", "not a calibration file"),
    (json.dumps({**CostModel().as_dict(), "version": VERSION + 1}), "version"),
    (json.dumps({**CostModel().as_dict(), "latency_s": -1.0}), "latency_s"),
    (json.dumps({**CostModel().as_dict(), "trace_ray_s": "fast"}), "trace_ray_s"),
    (json.dumps([1, 2]), "not a JSON object"),
], ids=["not-json", "version", "negative", "not-a-number", "not-an-object"])
def test_a_bad_calibration_file_is_refused_naming_it(tmp_path, text, problem):
    path = tmp_path / "costs.json"
    path.write_text(text)
    with pytest.raises(InputError, match=problem) as err:
        CostModel.load(path)
    assert str(path) in str(err.value)


def test_a_missing_calibration_file_is_named(tmp_path):
    with pytest.raises(InputError, match="no such calibration file") as err:
        CostModel.load(tmp_path / "absent.json")
    assert str(tmp_path / "absent.json") in str(err.value)


# -- the peer process -----------------------------------------------------------------------
def test_a_silent_or_dead_peer_is_an_error_not_a_hang(monkeypatch):
    monkeypatch.setattr(cal, "PEER_REPLY_TIMEOUT_S", 0.5)
    frames = cal.encode("rays", {"x": np.arange(10.0)})
    with cal.Peer() as peer:
        assert peer.round_trip(frames) > 0
        os.kill(peer.process.pid, signal.SIGSTOP)  # alive, but answers nothing
        try:
            start = time.perf_counter()
            with pytest.raises(cal.CalibrationError, match="did not answer a ray batch"):
                peer.round_trip(frames)
            assert time.perf_counter() - start < 60  # the 0.5 s timeout, not a hang
        finally:
            os.kill(peer.process.pid, signal.SIGCONT)
        peer.receive(5.0, "answer the delayed batch")
        peer.dealer.send_multipart(cal.encode("stop", {}))
        peer.process.join(10)
        with pytest.raises(cal.CalibrationError, match="exited"):
            peer.round_trip(frames)


# -- the fits -------------------------------------------------------------------------------
def test_fit_line_recovers_a_line_and_weights_pull_it_to_small_values():
    x = np.array([0.0, 1e3, 1e4, 1e5])
    assert np.allclose(cal.fit_line(x, 5e-5 + 2e-9 * x), (5e-5, 2e-9))
    y = 5e-5 + 2e-9 * x
    y[2] *= 3  # a mid-sized point off: unweighted, the intercept (latency) almost doubles
    plain, weighted = cal.fit_line(x, y), cal.fit_line(x, y, 1 / y ** 2)
    assert abs(plain[0] - 5e-5) > 2.5e-5 and abs(weighted[0] - 5e-5) < 5e-6


def test_wire_costs_fall_back_when_noise_leaves_a_negative_intercept():
    samples = [(50, 5e-5), (150_000, 3e-4), (1_500_000, 3e-3), (15_000_000, 3e-2)]
    latency_s, byte_s = cal.wire_costs(samples)
    assert 0 < latency_s <= 5e-5 and byte_s == pytest.approx(2e-9, rel=0.1)


def test_throughput_is_the_running_processes_at_their_cpu_cost_against_one_alone():
    # two processes each needing the CPU of one alone: twice the work; four on 2 cores: two
    # run at a time (their CPU per render is the same, their wall time twice as long)
    rounds = [{1: [1.0], 2: [1.0, 1.0], 4: [1.0, 1.0, 1.0, 1.0]}] * 3
    assert throughput_of(rounds, cores=2) == {1: 1.0, 2: 2.0, 4: 2.0}
    # contention: each of two processes needs 1.25x the CPU of one alone
    rounds = [{1: [1.0], 2: [1.25, 1.25], 4: [1.25, 1.25, 1.25, 1.25]}] * 3
    assert throughput_of(rounds, cores=2) == pytest.approx({1: 1.0, 2: 1.6, 4: 1.6})


def test_throughput_takes_medians_over_rounds_and_caps_at_the_cores():
    # one round twice as costly for every count moves nothing (medians); an alone render
    # slowed in one round does not make the others look faster than the cores give
    quiet = {1: [1.0], 2: [1.25, 1.25], 4: [1.25, 1.25, 1.25, 1.25]}
    slow = {k: [2 * s for s in v] for k, v in quiet.items()}
    assert throughput_of([quiet, slow, quiet], cores=2) == pytest.approx(
        {1: 1.0, 2: 1.6, 4: 1.6})
    noisy = [{1: [3.0], 2: [1.0, 1.0], 4: [1.5, 1.5, 1.5, 1.5]}] * 3
    assert throughput_of(noisy, cores=2) == {1: 1.0, 2: 2.0, 4: 2.0}


def test_load_costs_of_alike_sizes_are_ratios_of_totals():
    # 1,000 and 1,200 bytes (triangles): too alike to tell a fixed cost from a slope
    samples = [cal.LoadSample(1000, 10, 1e-3, 2e-3), cal.LoadSample(1200, 12, 2e-3, 6e-3)]
    assert cal.load_costs(samples) == pytest.approx((0.0, 3e-3 / 2200, 0.0, 8e-3 / 22))


def test_load_costs_fit_a_fixed_part_and_a_slope_over_sizes():
    def read(nbytes):
        return 4e-4 + nbytes * 1e-9

    def build(triangles):
        return 3e-4 + triangles * 1.5e-7

    # loads at one size but many of them, and builds of 2 to 16 domains' triangles: the
    # build's slope comes from the builds, each size counting once however many loads
    loads = [cal.LoadSample(b, t, read(b), build(t)) for b, t in ((50_000, 2_000),
                                                                 (100_000, 2_400)) * 500]
    builds = [(t, build(t)) for t in (4_400, 8_800, 17_600, 35_200) for _ in range(3)]
    read_fixed, per_byte, build_fixed, per_triangle = cal.load_costs(loads, builds)
    assert (read_fixed, per_byte) == pytest.approx((4e-4, 1e-9), rel=1e-6)
    assert (build_fixed, per_triangle) == pytest.approx((3e-4, 1.5e-7), rel=1e-6)
    # the model charges a domain 10x the calibration's size what the line says, where
    # ratios of totals at the calibration's sizes charged it 2.3x
    model = CostModel(read_fixed_s=read_fixed, load_byte_s=per_byte,
                      build_fixed_s=build_fixed, build_triangle_s=per_triangle)
    assert model.load_s(750_000, 22_000) == pytest.approx(read(750_000) + build(22_000))


def test_load_costs_fall_back_to_ratios_where_noise_makes_a_part_negative():
    # read time falling with size: a negative slope is noise, not a cost
    loads = [cal.LoadSample(1000, 10, 2e-3, 1e-3), cal.LoadSample(4000, 40, 1e-3, 4e-3)]
    read_fixed, per_byte, build_fixed, per_triangle = cal.load_costs(loads)
    assert (read_fixed, per_byte) == pytest.approx((0.0, 3e-3 / 5000))
    assert (build_fixed, per_triangle) == pytest.approx((0.0, 1e-4))


def test_merged_arrays_place_each_part_at_its_origin():
    from vastray.scene.store import DomainArrays

    one = DomainArrays(vertices=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32),
                       indices=np.array([[0, 1, 2]], np.uint32), origin=np.array([10., 0, 0]))
    two = DomainArrays(vertices=np.array([[0, 0, 0], [0, 0, 1], [0, 1, 0]], np.float32),
                       indices=np.array([[0, 2, 1]], np.uint32), origin=np.array([12., 0, 0]))
    merged = cal.merged_arrays([one, two])
    np.testing.assert_array_equal(merged.indices, [[0, 1, 2], [3, 5, 4]])
    np.testing.assert_array_equal(merged.vertices[3:], [[2, 0, 0], [2, 0, 1], [2, 1, 0]])
    np.testing.assert_array_equal(merged.origin, [10, 0, 0])


def test_merged_builds_span_one_domain_to_the_whole_store(store):
    builds = cal.time_merged_builds(Store(store), frozenset(), rounds=2)
    sizes = sorted({t for t, _ in builds})
    domains = [d.n_triangles for d in Store(store).domains if d.n_triangles > 0]
    assert sizes[-1] == sum(domains) and len(builds) == 2 * len(sizes)
    assert all(seconds > 0 for _, seconds in builds)


def test_a_load_times_its_read_in_wall_seconds_and_its_build_in_cpu_seconds(store, monkeypatch):
    # Embree builds a large domain on every core: the build is charged the CPU of all its
    # threads, which a node sharing its cores pays (wall time on the idle calibration
    # machine charged a CT scan's 25,000-triangle domain half of it)
    from vastray.scene.cache import DomainCache

    clock = {"cpu": 10.0}

    class CountingBVH(cal.DomainBVH):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            clock["cpu"] += 0.75  # what the build's threads took

    monkeypatch.setattr(cal, "DomainBVH", CountingBVH)
    monkeypatch.setattr(cal.time, "process_time", lambda: clock["cpu"])
    opened = Store(store)
    domain = next(d.id for d in opened.domains if d.n_triangles > 0)
    sample = cal._timed_load(DomainCache(opened, 1), domain)
    assert sample.build_s == pytest.approx(0.75)
    assert 0.0 < sample.read_s < 5.0
    # the bytes a load reads: the triangles and the attributes the cache keeps (none here)
    assert (sample.nbytes, sample.triangles) == (opened.domains[domain].read_bytes(frozenset()),
                                                 opened.domains[domain].n_triangles)


def test_trace_costs_fit_calls_take_medians_and_split_shading():
    def tile(noise: float) -> cal.TileTiming:
        calls = tuple((d, r, s, (3e-4 + r * 1e-6 if r else 5e-5) + s * 4e-7 + noise * (d == 1))
                      for d, r, s in ((0, 100, 0), (1, 1000, 500), (2, 0, 5000), (0, 2000, 100),
                                      (3, 0, 300), (4, 400, 4000)))
        return cal.TileTiming(camera_s=1e-4, paths=1000, calls=calls, shade_s=3500 * 2e-7)

    costs = cal.trace_costs([tile(0.0), tile(0.5), tile(0.0)])  # one stall, out-voted
    assert costs["activation_s"] == pytest.approx(3e-4, rel=1e-6)
    assert costs["shadow_activation_s"] == pytest.approx(5e-5, rel=1e-6)
    assert costs["shadow_ray_s"] == pytest.approx(4e-7, rel=1e-6)
    assert costs["shade_ray_s"] == pytest.approx(2e-7)
    assert costs["trace_ray_s"] == pytest.approx(8e-7, rel=1e-6)
    assert costs["camera_ray_s"] == pytest.approx(1e-7)


@pytest.mark.slow
def test_the_default_calibration_measures_every_constant(store):
    model = cal.calibrate(store)  # about a minute on a quiet machine
    values = {name: getattr(model, name) for name in CONSTANTS if name not in SET_UP_COSTS}
    assert all(math.isfinite(v) and v > 0 for v in values.values()), values
    # set-up costs are differences clamped at 0, as in the quick calibration's test: with a
    # node's own code charged (``sim.meter``) every calibration of session 37 measured 0
    set_up = {name: getattr(model, name) for name in SET_UP_COSTS}
    assert all(0.0 <= v < 0.5 for v in set_up.values()), set_up
    assert not model.machine["calibration"]["quick"]
