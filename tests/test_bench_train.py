"""`mrrig bench train`: its table, its JSON and the scaling it judges (issue 27)."""

import json
import tempfile

import pytest

from mrrig.offline.bench.train import main, scaling, scaling_lines


def _row(samples: int, wall_s: float) -> dict:
    return {
        "samples": samples,
        "wall_s": wall_s,
        "kalman_s": 0.0,
        "exclusion_s": 0.0,
        "lm_s": 1.0,
        "epochs": 10,
        "rest_s": 0.0,
        "peak_rss_mb": 100.0,
        "data_rss_mb": 50.0,
        "excluded_samples": 0,
        "holdout_et": 0.05,
        "lm_rows": 1000,
    }


def test_scaling_shows_the_raw_per_sample_ratio_and_the_marginal_costs_spread():
    # the wall times of the run in docs/research-notes.md (10k to 10M samples)
    rows = [_row(10_000, 7.6), _row(100_000, 17.4), _row(1_000_000, 33.7), _row(10**7, 136.5)]
    sc = scaling(rows)
    assert (sc["from"], sc["to"]) == (100_000, 10**7)  # 10k is below the base
    assert sc["per_sample_us"] == pytest.approx([174.0, 13.65])
    assert sc["per_sample_ratio"] == pytest.approx(13.65 / 174.0)
    assert not sc["per_sample_within_factor"]  # it falls 12x: outside a factor of 2
    marginal = [st["marginal_us"] for st in sc["marginal_steps"]]
    assert marginal == pytest.approx([16.3 / 0.9, 102.8 / 9.0])
    assert sc["marginal_spread"] == pytest.approx(marginal[0] / marginal[1])
    assert sc["marginal_within_factor"]
    text = "\n".join(scaling_lines(sc))
    assert "x 0.078 (within a factor of 2: no)" in text
    assert "largest / smallest 1.59 (within a factor of 2: yes)" in text
    # a marginal cost that grows past the factor is called so
    grown = scaling([_row(100_000, 10.0), _row(200_000, 11.0), _row(300_000, 14.0)])
    assert grown["marginal_spread"] == pytest.approx(3.0) and not grown["marginal_within_factor"]
    assert scaling([_row(100_000, 10.0)]) is None


@pytest.mark.long
def test_bench_train_runs_each_size_in_its_own_process_and_writes_its_numbers(
    tmp_path, monkeypatch, capsys
):
    # a pool of 3 simulated runs (6000 samples), cached in this test's own folder
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    out = tmp_path / "bench.json"
    sizes = [5_000, 10_000, 20_000]
    argv = ["--sizes", ",".join(map(str, sizes)), "--epochs", "5", "--pool-runs", "3"]
    assert main([*argv, "--json", str(out)]) == 0
    assert list(tmp_path.glob("mrrig-bench-train-pool-*-3.npz"))
    text = capsys.readouterr().out
    data = json.loads(out.read_text())
    rows = data["sizes"]
    assert [r["samples"] for r in rows] == sizes
    for r in rows:
        assert r["wall_s"] > r["lm_s"] > 0.0 and 1 <= r["epochs"] <= 5
        assert r["peak_rss_mb"] >= r["data_rss_mb"] > 0.0
        assert 0.0 < r["holdout_et"] < 1.0 and 0 < r["lm_rows"] < r["samples"]
        assert f"\n{r['samples']:>10} {r['wall_s']:8.1f}" in text
    assert data["scaling"] == scaling(rows)
    assert (data["scaling"]["from"], data["scaling"]["to"]) == (5_000, 20_000)
    assert "\n".join(scaling_lines(data["scaling"])) in text
