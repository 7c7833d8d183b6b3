"""``fingertrack bench gestures --quick``: the results file and the goals it must meet."""
import json

import pytest

from service.bench import gestures


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("gestures")
    gestures.run(out, quick=True, progress=False)
    return out, json.loads((out / "results.json").read_text())


def test_results_file_has_every_field(quick):
    out, res = quick
    assert set(res["gestures"]) == {"point", "grasp", "pinch", "open"}
    for r in res["gestures"].values():
        assert {"precision", "recall", "f1", "onset_median_s", "onset_p95_s", "release_median_s", "release_p95_s"} <= set(r)
        assert r["true_count"] > 0
    assert isinstance(res["chatter"], int)
    assert set(res["ray_error_deg"]) == {"median", "p95"}
    assert "| gesture |" in (out / "summary.md").read_text()


def test_goals_on_the_quick_session(quick):
    _, res = quick
    for g, r in res["gestures"].items():
        assert r["f1"] >= 0.98, g
        assert r["onset_median_s"] < 0.060, g
    assert res["chatter"] == 0
    assert res["ray_error_deg"]["median"] < 2.0


def test_scoring_matches_overlapping_intervals():
    sessions = [{"detected": {"point": [[1.0, 2.0], [3.0, 3.05]], "grasp": [], "pinch": [], "open": []},
                 "truth": {"point": [[0.98, 1.97], [5.0, 6.0]], "grasp": [], "pinch": [], "open": []},
                 "ray_error_deg": [0.5, 1.5]}]
    res = gestures.score(sessions)
    p = res["gestures"]["point"]
    assert p["precision"] == 0.5 and p["recall"] == 0.5
    assert p["onset_median_s"] == pytest.approx(0.02) and p["release_median_s"] == pytest.approx(0.03)
    assert res["chatter"] == 1
    assert res["ray_error_deg"]["median"] == pytest.approx(1.0)
