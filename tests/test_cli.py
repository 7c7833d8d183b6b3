"""The command line, through ``service.cli.main`` (the same code the console script runs)."""
import csv

import numpy as np
import pytest

from service.cli import main


def test_simulate_then_estimate_with_truth(tmp_path, capsys):
    rec = tmp_path / "grasp.jsonl"
    assert main(["simulate", "--motion", "grasp", "--tm", "1", "--noise", "none", "--seed", "3", "--out", str(rec)]) == 0
    out_csv = tmp_path / "angles.csv"
    assert main(["estimate", str(rec), "--estimator", "integration", "--init-from-truth", "--truth", "--out", str(out_csv)]) == 0
    text = capsys.readouterr().out
    assert "RMS error per joint, degrees" in text
    rows = list(csv.DictReader(out_csv.open()))
    assert rows[0].keys() == {"t", "finger", "mcp", "pip", "dip", "mode"}
    assert {r["finger"] for r in rows} == {"thumb", "index", "middle", "ring", "little"}
    last_index = [r for r in rows if r["finger"] == "index"][-1]
    # the grasp ends at MCP 90, PIP/DIP 85 degrees; noise-free integration from the truth is exact
    assert np.degrees(float(last_index["mcp"])) == pytest.approx(90.0, abs=0.05)
    assert np.degrees(float(last_index["dip"])) == pytest.approx(85.0, abs=0.05)
    thumb = [r for r in rows if r["finger"] == "thumb"][0]
    assert thumb["dip"] == ""


def test_estimate_list_names_every_estimator(capsys):
    assert main(["estimate", "--list"]) == 0
    names = [line.split("\t")[0] for line in capsys.readouterr().out.splitlines()]
    assert {"vector", "integration", "switching", "madgwick", "ekf", "cf", "chain"} <= set(names)


def test_bad_arguments_give_clear_errors(tmp_path, capsys):
    rec = tmp_path / "r.jsonl"
    main(["simulate", "--motion", "open", "--out", str(rec)])
    assert main(["estimate", str(rec), "--estimator", "kalman", "--out", str(tmp_path / "x.csv")]) == 2
    assert "unknown estimator 'kalman'" in capsys.readouterr().err
    assert main(["estimate", str(rec), "--estimator", "madgwick", "--param", "bta=1", "--out", str(tmp_path / "x.csv")]) == 2
    assert "bta" in capsys.readouterr().err
    bad = tmp_path / "bad.jsonl"
    lines = rec.read_text().splitlines()
    lines[5] = '{"type":"imu","t":0.0,"id":"index.1","gyr":[0,0],"acc":[0,0,0]}'
    bad.write_text("\n".join(lines) + "\n")
    assert main(["estimate", str(bad), "--out", str(tmp_path / "y.csv")]) == 2
    err = capsys.readouterr().err
    assert "bad.jsonl:6" in err and "gyr" in err
    with pytest.raises(SystemExit):
        main(["simulate", "--motion", "grasp", "--tm", "-1", "--out", str(tmp_path / "z.jsonl")])


def test_simulate_with_an_occlusion(tmp_path):
    import json
    rec = tmp_path / "occ.jsonl"
    assert main(["simulate", "--motion", "point", "--occlusion", "0.5:1.0", "--optical-rate", "60", "--out", str(rec)]) == 0
    poses = [json.loads(l) for l in rec.read_text().splitlines() if '"pose"' in l]
    invalid = [p["t"] for p in poses if not p["valid"]]
    assert invalid and min(invalid) >= 0.5 and max(invalid) < 1.0
    assert abs(poses[1]["t"] - poses[0]["t"] - 1 / 60) < 1e-12
    with pytest.raises(SystemExit):
        main(["simulate", "--occlusion", "2:1", "--out", str(rec)])


def test_a_dotted_param_sets_a_nested_setting(tmp_path, capsys):
    from service.cli import _parse_params
    from service.estimators.inertial import InertialFingerSettings

    params = _parse_params(["core.tau_acc_s=2", "core.scale_sigma_init=0", "second_reference=false"], None)
    settings = InertialFingerSettings(**params)
    assert settings.core.tau_acc_s == 2.0 and settings.core.scale_sigma_init == 0.0
    assert settings.second_reference is False
    assert settings.core.bias_clip_deg_s == InertialFingerSettings().core.bias_clip_deg_s    # the rest untouched
    rec = tmp_path / "g.jsonl"
    main(["simulate", "--motion", "grasp", "--tm", "1", "--noise", "both", "--out", str(rec)])
    outs = []
    for extra in ([], ["--param", "core.tau_acc_s=0.5"]):
        out_csv = tmp_path / f"a{len(extra)}.csv"
        assert main(["estimate", str(rec), "--estimator", "inertial", *extra, "--out", str(out_csv)]) == 0
        outs.append(out_csv.read_text())
    assert outs[0] != outs[1]                                   # the nested setting reached the filter
    assert main(["estimate", str(rec), "--estimator", "inertial", "--param", "core.tau_ac=2",
                 "--out", str(tmp_path / "x.csv")]) == 2
    assert "tau_ac" in capsys.readouterr().err
    assert main(["estimate", str(rec), "--estimator", "inertial", "--param", "core=2", "--param", "core.tau_acc_s=1",
                 "--out", str(tmp_path / "x.csv")]) == 2
    assert "also given a value" in capsys.readouterr().err
    assert main(["estimate", str(rec), "--estimator", "inertial", "--param", "core.=1",
                 "--out", str(tmp_path / "x.csv")]) == 2
    assert "empty name" in capsys.readouterr().err
