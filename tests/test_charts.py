"""model.charts: what the speed-against-accuracy chart puts on its front."""

from model.charts import onchip_point, pareto_front


def method(name, us, rmse_m, photon=False, bit_exact=False):
    return {"name": name, "us_per_waveform": us, "photon": photon, "bit_exact": bit_exact,
            "summary": {"rmse_m": rmse_m, "detection_rate": 1.0}}


ACC = {"methods": [method("fast_rough", 10.0, 0.20), method("slow_fine", 1e4, 0.02),
                   method("dominated", 100.0, 0.30), method("unanswered", 50.0, None),
                   method("photons", 5.0, 0.01, photon=True)],
       "targets": []}


def test_the_front_is_the_undominated_waveform_methods():
    # the photon counter (fastest and most accurate here, on its own shots) is not on it
    assert pareto_front(ACC) == [(10.0, 20.0), (1e4, 2.0)]


def test_the_chip_joins_the_front_where_the_acc_is_scored():
    fpga = {"us_per_waveform": 1.0, "key": "albcap_filter_detect[lanes=10]"}
    acc = {**ACC, "targets": [{"id": "onchip_speed", "fpga": fpga, "chip_rmse_m": 0.10}]}
    assert onchip_point(acc) == (1.0, 10.0, "albcap_filter_detect[lanes=10]")
    # the chip is faster and better than fast_rough, which leaves the front
    assert pareto_front(acc) == [(1.0, 10.0), (1e4, 2.0)]


def test_no_chip_without_an_fpga_figure():
    acc = {**ACC, "targets": [{"id": "onchip_speed", "chip_rmse_m": 0.10}]}
    assert onchip_point(acc) is None
    assert pareto_front(acc) == pareto_front(ACC)


def test_chart_writes_the_rescored_targets_back(tmp_path):
    """``albcap chart`` scores the targets with the latest recorded figures (the speed and
    builds benches run after the sweep) and writes them into the accuracy JSON, so that the
    JSON and the page agree."""
    import json
    from pathlib import Path

    from firmware_host.cli import main
    from model.accuracy import score

    rec = Path(__file__).resolve().parent.parent / "docs" / "figures" / "accuracy.json"
    acc = json.loads(rec.read_text())
    stale = {**acc, "targets": [{**t, "value": -1.0} for t in acc["targets"]]}
    path = tmp_path / "accuracy.json"
    path.write_text(json.dumps(stale))
    assert main(["chart", "--accuracy", str(path), "--regimes", str(tmp_path / "none.json"),
                 "--out-dir", str(tmp_path)]) == 0
    back = json.loads(path.read_text())
    assert back["targets"] == score(acc)["targets"]
    assert all(t["value"] != -1.0 for t in back["targets"])
