"""The command line, through ``service.cli.main`` (the same code the console script runs)."""
import argparse
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

    params = _parse_params(["core.tau_acc_s=2", "core.scale_sigma_init=0", "second_reference=false"])
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


def test_beta_is_short_for_the_beta_param(tmp_path, capsys):
    rec = tmp_path / "g.jsonl"
    main(["simulate", "--motion", "grasp", "--tm", "0.5", "--noise", "white", "--out", str(rec)])
    outs = {}
    for name, extra in (("default", []), ("beta", ["--beta", "0.5"]), ("param", ["--param", "beta=0.5"])):
        assert main(["estimate", str(rec), "--estimator", "madgwick", *extra, "--out", str(tmp_path / f"{name}.csv")]) == 0
        outs[name] = (tmp_path / f"{name}.csv").read_text()
    assert outs["beta"] == outs["param"] != outs["default"]
    capsys.readouterr()
    assert main(["estimate", str(rec), "--estimator", "chain", "--beta", "0.5", "--out", str(tmp_path / "x.csv")]) == 2
    assert "beta" in capsys.readouterr().err                    # chain has no beta: refused by name
    assert main(["estimate", str(rec), "--estimator", "madgwick", "--beta", "fast", "--out", str(tmp_path / "x.csv")]) == 2
    assert "beta" in capsys.readouterr().err


def _subcommands(parser) -> dict:
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def _help(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as done:
        main([*argv, "--help"])
    assert done.value.code == 0
    return capsys.readouterr().out


def test_each_benchmark_has_its_own_help(capsys):
    from service.cli import build_parser
    names = list(_subcommands(_subcommands(build_parser())["bench"]))
    assert set(names) >= {"paper", "gestures", "peers", "latency", "load", "robustness"}
    helps = {name: _help(["bench", name], capsys) for name in names}
    assert len(set(helps.values())) == len(names)               # no two the same
    assert "--hands" in helps["load"] and "--hands" not in helps["paper"]
    assert "--seeds" in helps["paper"] and "--seeds" not in helps["latency"]
    assert "--data" in helps["peers"] and "--data" not in helps["gestures"]
    with pytest.raises(SystemExit):                              # an option of another benchmark is refused
        main(["bench", "latency", "--hands", "2", "--out", "x"])
    assert "unrecognized arguments: --hands" in capsys.readouterr().err


def test_every_option_of_every_command_says_what_it_does_and_its_default():
    from service.cli import build_parser
    commands = dict(_subcommands(build_parser()))
    commands.update({f"bench {k}": v for k, v in _subcommands(commands.pop("bench")).items()})
    assert {"glove", "watch", "lsl", "schema", "bench paper"} <= set(commands)
    for name, parser in commands.items():
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            assert action.help, f"{name} {action.option_strings or action.dest} has no help"
            if action.default not in (None, False, [], argparse.SUPPRESS) and not action.required:
                assert "default" in action.help, f"{name} {action.option_strings} does not state its default"


def test_quick_descriptions_say_what_quick_runs(capsys):
    """The --quick help texts against the constants the benchmarks run with."""
    from service.bench import gestures, paper, peers, robustness
    d = paper.durations(True)
    text = " ".join(_help(["bench", "paper"], capsys).split())
    assert f"{len(d)} durations from {d[0]:g} s to {d[-1]:.3g} s and one seed" in text
    assert f"instead of {len(paper.durations(False))} up to {paper.durations(False)[-1]:g} s" in text
    text = " ".join(_help(["bench", "gestures"], capsys).split())
    q, f, qi, fi = gestures.QUICK, gestures.FULL, gestures.QUICK_IDLE, gestures.FULL_IDLE
    assert (f"{len(q['seeds'])} trials of {q['duration_s']:g} s and {len(qi['seeds'])} idle of {qi['duration_s']:g} s "
            f"instead of {len(f['seeds'])} of {f['duration_s']:g} s and {len(fi['seeds'])} idle of {fi['duration_s']:g} s") in text
    from service.sim.gesture_script import make_trial
    enrolment = make_trial(q["seeds"][0], q["duration_s"]).scored_from_s - make_trial(q["seeds"][0], q["duration_s"], enrolment=False).scored_from_s
    assert f"after a {enrolment:.0f} s enrolment" in text
    text = " ".join(_help(["bench", "peers"], capsys).split())
    assert f"the first {peers.QUICK_N} samples of the first three trials" in text
    text = " ".join(_help(["bench", "robustness"], capsys).split())
    q, f = robustness.QUICK, robustness.FULL
    assert f"{q['messages']} fuzz messages, {q['extreme_seconds']:g} s of extremes on two probes" in text
    assert len(q["probes"]) == 2 and f["probes"] is None
    assert f"{q['readers']} readers, {q['connects']} connects, one kill and a {q['soak_seconds']:g} s soak" in text
    assert q["kill_trials"] == 1 and f["kill_trials"] == 3
    assert (f"instead of {f['messages']} messages, {f['extreme_seconds']:g} s on every probe, {f['readers']} readers, "
            f"{f['connects']} connects, three kills and a {f['soak_seconds']:g} s soak") in text
    assert f"default {f['soak_seconds']:g}; {q['soak_seconds']:g} with --quick" in text
    assert f"default {f['messages']}; {q['messages']} with --quick" in text


@pytest.mark.parametrize("command", [["lsl", "--session", "a"], ["watch"], ["glove"]])
def test_a_bad_service_url_is_refused_by_name_without_a_traceback(command, capsys):
    with pytest.raises(SystemExit) as err:
        main([*command, "--url", "notaurl", "--token", "tok-not-shown"])
    assert err.value.code == 2
    text = capsys.readouterr().err
    assert "--url" in text and "notaurl" in text
    assert "tok-not-shown" not in text and "Traceback" not in text


def test_the_accuracy_quick_description_says_which_trials_run(tmp_path, capsys, monkeypatch):
    """The trials bench accuracy builds, quick and full (taken where they go to the worker pool,
    before any is run), against what its --quick help says."""
    from service.bench import accuracy

    class Planned(Exception):
        pass

    class Pool:
        def __init__(self, max_workers):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def map(self, fn, jobs):
            raise Planned(list(jobs))

    monkeypatch.setattr(accuracy, "ProcessPoolExecutor", Pool)

    def plan(quick: bool) -> dict:
        with pytest.raises(Planned) as planned:
            accuracy.run(tmp_path, quick=quick, workers=2, progress=False)
        jobs = planned.value.args[0]
        main = [j for j in jobs if j[0].coupling is None and not j[0].metacarpus_imu]
        coupled = [j for j in jobs if j[0].coupling is not None]
        imu = [j for j in jobs if j[0].metacarpus_imu]
        return {"trials": len({j[0].seed for j in main}), "seconds": {j[0].duration_s for j in main},
                "estimators": {j[2] for j in main}, "couplings": len({j[0].coupling for j in coupled}),
                "coupled_estimators": {j[2] for j in coupled}, "imu_trials": len({j[0].seed for j in imu}),
                "imu_estimators": {j[2] for j in imu}}
    quick, full = plan(True), plan(False)
    assert quick == {"trials": 1, "seconds": {6.0}, "estimators": {"chain", "ekf", "vector"}, "couplings": 1,
                     "coupled_estimators": {"chain"}, "imu_trials": 1, "imu_estimators": {"chain"}}
    assert full == {"trials": 5, "seconds": {12.0}, "estimators": {e[0] for e in accuracy.ESTIMATORS}, "couplings": 4,
                    "coupled_estimators": {"chain", "ekf"}, "imu_trials": 5, "imu_estimators": {"chain"}}
    text = " ".join(_help(["bench", "accuracy"], capsys).split())
    assert ("one 6 s trial with chain, ekf and vector, one coupling trial and one back-of-hand IMU trial with chain, "
            "instead of 5 trials of 12 s with every estimator, 4 coupling trials with chain and ekf and 5 back-of-hand "
            "IMU trials") in text


def test_the_bench_help_names_every_benchmark(capsys):
    from service.cli import build_parser
    names = list(_subcommands(_subcommands(build_parser())["bench"]))
    text = " ".join(_help([], capsys).split())
    topics = {"paper": "the paper's experiment", "gestures": "gestures", "peers": "peer libraries",
              "latency": "service latency", "cpu": "CPU per hand", "load": "service load", "robustness": "robustness",
              "accuracy": "accuracy in use", "switch": "estimator switch"}
    assert set(names) == set(topics)
    assert all(topic in text for topic in topics.values()), text
