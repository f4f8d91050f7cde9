"""``bench/convergence.py``'s table and bias/variance split, on hand-made reports (the script
itself renders for a minute or more, so it is not run here)."""

from __future__ import annotations

import math

import pytest
from bench_modules import load_bench

convergence = load_bench("convergence")


def report(scheduler="async", nodes=2, errors=(1e-1, 1e-2, 1e-3), estimated=None,
           seconds=(1.0, 2.0, 4.0), stopped_by="spp"):
    estimated = estimated or [None] + [e * 0.9 for e in errors[1:]]
    passes = [{"pass": k, "seconds": t, "spp": 2 ** k, "rel_mse": e, "estimated_rel_mse": v}
              for k, (t, e, v) in enumerate(zip(seconds, errors, estimated, strict=True))]
    return {"scheduler": scheduler, "options": {"nodes": nodes}, "stopped_by": stopped_by,
            "passes": [{"pass": -1, "seconds": 0.0, "spp": 0, "rel_mse": None}, *passes]}


def test_summary_gives_times_to_each_error_efficiency_and_the_last_pass():
    row = convergence.summarize(report(errors=(1e-1, 1e-2, 2e-3)))
    assert row.to_threshold[0] == pytest.approx(2.0)  # reached exactly at a pass
    assert row.to_threshold[1] is None  # 2e-3 never reaches 1e-3
    assert (row.spp, row.final_rel_mse, row.first_pass_s) == (4, 2e-3, 1.0)
    assert row.efficiency == pytest.approx(1 / (2e-3 * 4.0))
    assert (row.scheduler, row.nodes, row.stopped_by) == ("async", 2, "spp")


def test_time_to_error_is_interpolated_log_log_between_the_bracketing_passes():
    # relMSE 1e-1 at 1 s, 1e-3 at 4 s: 1e-2 lies halfway in log error, so at 2 s
    row = convergence.summarize(report(errors=(1e-1, 1e-1, 1e-3), seconds=(0.5, 1.0, 4.0)))
    assert row.to_threshold == [pytest.approx(2.0), pytest.approx(4.0)]


def test_summary_refuses_a_report_without_a_reference():
    bare = report()
    for p in bare["passes"]:
        p["rel_mse"] = None
    with pytest.raises(ValueError, match="--reference"):
        convergence.summarize(bare)


def test_bias_variance_split_against_the_estimate_and_the_lossless_twin():
    lossy = report(errors=(1e-1, 1e-2, 3e-3), estimated=[None, 9e-3, 2e-3])
    twin = report(errors=(1e-1, 1e-2, 2.5e-3))
    split = convergence.bias_variance(lossy, twin)
    assert split["variance"] == 2e-3 and split["rel_mse"] == 3e-3
    assert split["bias2"] == pytest.approx(1e-3)
    assert split["bias2_paired"] == pytest.approx(0.5e-3)
    assert "bias2_paired" not in convergence.bias_variance(lossy)
    # the reference's own noise (inside every relMSE against it) comes out of bias^2 too,
    # not out of the paired one (both runs hold it)
    noisy = convergence.bias_variance(lossy, twin, reference_noise=0.4e-3)
    assert noisy["reference_variance"] == 0.4e-3
    assert noisy["bias2"] == pytest.approx(0.6e-3)
    assert noisy["bias2_paired"] == pytest.approx(0.5e-3)


def test_markdown_table_has_a_row_per_run_and_labels_the_lossy_one():
    rows = [convergence.summarize(report("reference", None, errors=(1e-2, 1e-3, 0.0))),
            convergence.summarize(report("temporal", 2), lossy=True)]
    rows[1].process_s = 3.25
    lines = convergence.markdown_table(rows).splitlines()
    assert len(lines) == 4
    assert all(line.count("|") == lines[0].count("|") for line in lines)
    assert "1 (single process)" in lines[2] and "∞" in lines[2]  # relMSE 0: efficiency ∞
    assert "temporal --simplified portal (lossy) | 2 |" in lines[3] and "| 3.25 |" in lines[3]
    assert math.isinf(rows[0].efficiency)


def test_plan_runs_the_reference_first_and_one_lossy_run():
    quick, full = convergence.plan(True), convergence.plan(False)
    for runs in (quick, full):
        assert runs[0].name == "reference-local" and sum(r.lossy for r in runs) == 1
        assert len({r.name for r in runs}) == len(runs)
    assert {r.nodes for r in quick if r.scheduler == "async"} == {1, 2, 4}
    assert len(full) == 2 + 7 * 3 + 1


def cal_report(points, noise_free=True):
    """A report with passes (spp, rel_mse, ci95)."""
    return {"passes": [{"pass": -1, "spp": 0, "rel_mse": None}]
            + [{"pass": k, "spp": spp, "rel_mse": e, "estimated_rel_mse_ci95": ci,
                "estimated_rel_mse": None if ci is None else sum(ci) / 2}
               for k, (spp, e, ci) in enumerate(points)]}


def test_coverage_counts_passes_from_4_spp_against_the_true_error():
    noise = 1e-3  # the reference's own relMSE, subtracted from every relMSE
    rep = cal_report([(2, 0.5, [0.0, 0.1]),  # below 4 spp: not counted
                      (4, 0.051, [0.04, 0.06]),  # true 0.05: inside
                      (8, 0.031, [0.01, 0.02]),  # true 0.03: above (optimistic)
                      (16, 0.006, [0.01, 0.02])])  # true 0.005: below (pessimistic)
    assert convergence.coverage([rep], noise) == {"passes": 3, "inside": 1, "below": 1,
                                                  "above": 1}
    assert convergence.reference_noise(cal_report([(1, None, [1, 3]), (2, None, [2, 4])])) == 3


def test_target_and_oracle_use_the_true_error_of_the_same_seed():
    a = cal_report([(8, 0.02, None), (16, 0.011, None), (24, 0.007, None)])
    b = cal_report([(8, 0.03, None), (16, 0.009, None), (24, 0.005, None)])
    c = cal_report([(8, 0.03, None), (16, 0.013, None), (24, 0.005, None)])
    target = convergence.choose_target([a, b, c], 0.0, at_spp=16)
    assert target == pytest.approx(0.011)  # the median at 16 spp
    assert convergence.oracle_spp(a, 0.0, target) == 16
    assert convergence.oracle_spp(c, 0.0, target) == 24
    assert convergence.oracle_spp(a, 0.0, 1e-4) is None
    with pytest.raises(ValueError):
        convergence.choose_target([a], 0.0, at_spp=32)


def test_calibration_figures_and_table():
    runs = [convergence.TargetRun(seed=s, stop_spp=stop, stopped_by="target-error",
                                  stop_bound=0.01, true_error=e, target=0.01, oracle=o,
                                  grey_error=g, ci95=[0.005, 0.012])
            for s, (stop, e, o, g) in enumerate([(24, 0.008, 16, 0.007), (32, 0.009, 16, 0.02),
                                                 (24, 0.012, 24, 0.009), (64, 0.02, None, 0.02)])]
    cov = [{"passes": 10, "inside": 9, "below": 1, "above": 0},
           {"passes": 10, "inside": 8, "below": 0, "above": 2}]
    f = convergence.calibration_figures(cov, runs)
    assert f["ci_coverage"] == pytest.approx(0.85) and f["passes"] == 20
    assert f["target_met_share"] == pytest.approx(0.5) and f["runs"] == 4
    assert f["spp_over_oracle"] == pytest.approx(1.5) and f["spp_over_oracle_max"] == 2.0
    assert f["target_met_share_grey"] == pytest.approx(0.5)
    assert f["ci_coverage_grey_at_stop"] == pytest.approx(0.5)
    scene = convergence.CalScene("rm", None, "pt", nodes=2)
    assert scene.args(48, 36)[:6] == ["--integrator", "pt", "--width", "48", "--height", "36"]
    assert scene.args(48, 36)[-4:] == ["--nodes", "2", "--scheduler", "async"]
    lines = convergence.calibration_table([(scene, cov[0], 1e-5, 0.01, runs)]).splitlines()
    assert len(lines) == 3 and all(x.count("|") == lines[0].count("|") for x in lines)
    assert "| 24,32,24,64 | 16,16,24,— | 1.50 (2.00) |" in lines[2]
    f["scenes"], f["seconds"] = 1, 3.0
    line = convergence.calibration_line(f)
    assert "ci_coverage=0.850" in line and "target_met_share=0.500" in line
    assert "spp_over_oracle=1.50 (max 2.00)" in line


def test_the_hidden_lamp_scene_hides_its_light_in_a_cup_under_the_ceiling(tmp_path):
    # The heavy-tailed calibration scene: a mesh and a SCENE.toml vastray reads, the point
    # light inside the cup (below its rim, above its floor), the rim below the ceiling.
    import numpy as np
    import trimesh
    from bench_scenes import hidden_lamp_scene  # bench/ is on sys.path (load_bench)

    from vastray.render.scene_config import load_scene_config
    ply, toml = hidden_lamp_scene(tmp_path, cup=0.5, depth=0.2, gap=0.1)
    mesh = trimesh.load(ply, force="mesh", process=False)
    assert mesh.bounds[1][1] == pytest.approx(2.02)  # the ceiling's top
    light = load_scene_config(toml).lights[0]
    y = float(light.position[1])
    assert 2.0 - 0.1 - 0.2 - 0.05 < y < 2.0 - 0.1  # between the cup's floor and its rim
    assert np.ptp(np.asarray(light.intensity)) > 0  # coloured
