"""The orientation cores on real recordings (BROAD trials in the shared data folder)."""
from pathlib import Path

import numpy as np
import pytest

from service.bench.peers import _ours, inclination_rmse_deg, load_trial

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "broad"
TRIAL = DATA / "01_undisturbed_slow_rotation_A.mat"
pytestmark = pytest.mark.skipif(not TRIAL.exists(), reason=f"BROAD data not found at {DATA}")

N = 20000
# recorded with this code on 2026-11-22 (first 20000 samples: 35 s of rest, then slow rotation)
EXPECTED = {"madgwick": 0.5313453049876002, "ekf": 0.535982810494175, "inertial": 0.3332187141791665}


@pytest.fixture(scope="module")
def trial():
    return load_trial(TRIAL)


@pytest.mark.parametrize("kind", ["inertial", "madgwick", "ekf"])
def test_imu_only_core_reproduces_its_recorded_result(trial, kind):
    q, _ = _ours(kind, False, trial["gyr"][:N], trial["acc"][:N], trial["quat"][:N], 1.0 / trial["rate"])
    err = inclination_rmse_deg(q, trial["quat"][:N], trial["movement"][:N])
    assert err == pytest.approx(EXPECTED[kind], abs=1e-6)
    assert err < 1.0


@pytest.mark.parametrize("kind", ["inertial", "madgwick", "ekf"])
@pytest.mark.parametrize("optical", [False, True])
def test_at_rest_gravity_matches_the_optical_truth(trial, kind, optical):
    # samples 8000-9500 are still (before the first movement at 9656), 28 s after the start
    q, _ = _ours(kind, optical, trial["gyr"][:9500], trial["acc"][:9500], trial["quat"][:9500], 1.0 / trial["rate"])
    rest = slice(8000, 9500)
    assert not trial["movement"][rest].any()
    assert inclination_rmse_deg(q[rest], trial["quat"][rest], np.ones(1500, bool)) < 1.0


def test_bad_data_folder_is_a_clear_error(tmp_path):
    from service.bench import peers
    with pytest.raises(ValueError, match="no .mat trials"):
        peers.run(tmp_path, tmp_path / "out", quick=True, progress=False)
