"""The benchmark and the end-to-end evaluation run and report what they measured."""

from markerpose.experiments import bench, endtoend


def test_bench_runs_and_reports_every_configuration():
    res = bench.main({"pairs": 1, "repeats": 2, "configs": ["classical (paper)", "classical + sub-pixel"]}, progress=False)
    assert set(res["configs"]) == {"classical (paper)", "classical + sub-pixel"}
    assert res["reference"] == "classical (paper)"
    assert res["configs"]["classical (paper)"]["speed_vs_reference"] == 1.0
    assert res["configs"]["classical + sub-pixel"]["found"] == 1.0
    assert "classical + sub-pixel" in bench.report(res)


def test_end_to_end_counts_detections_and_errors():
    res = endtoend.main({"pairs": 2, "sets": ("standard",), "configs": ["classical + sub-pixel + bias + rigid"]}, progress=False)
    s = res["sets"]["standard"]["classical + sub-pixel + bias + rigid"]
    assert s["pairs"] == 2 and s["detected"] == 1.0
    assert s["center_median_px"] < 0.1 and s["t_median_mm"] < 0.05
    assert "standard" in endtoend.report(res)
