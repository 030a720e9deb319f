import json

import pytest

from uwb_env.cli import check_policies, main


def test_simulate_prints_a_summary(capsys):
    assert main(["simulate", "--steps", "30", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["calibration round steps at dt_s"] == 5
    assert summary["anchor drift after run, mean (m)"] > 0


def test_bad_config_file_is_reported(tmp_path, capsys):
    path = tmp_path / "bad.yml"
    path.write_text("ranging:\n  nlos_prob: 0.3\n")
    assert main(["simulate", "--steps", "5", "--config", str(path)]) == 2
    assert "ranging.nlos_prob" in capsys.readouterr().err


def test_help_lists_every_command(capsys):
    import pytest

    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for command in ("simulate", "evaluate", "train"):
        assert command in out


def test_emulate_prints_the_port_names(capsys):
    assert main(["emulate", "--duration", "0.3"]) == 0
    out = capsys.readouterr().out
    assert "anchor" in out and "/dev/pts/" in out and "tag_2" in out


@pytest.mark.parametrize(("argv", "names"), [
    (["evaluate", "--policies", "learned:nope.zip", "--seeds", "1"], "--policies learned:nope.zip"),
    (["simulate", "--config", "missing.yml"], "--config missing.yml"),
    (["train", "--env-config", "missing.yml"], "--env-config missing.yml"),
])
def test_cli_mistakes_are_one_line_naming_the_argument(argv, names, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and names in err, err


def test_unknown_hyperparameter_is_one_line_and_leaves_no_folder(capsys, tmp_path):
    pytest.importorskip("stable_baselines3")
    out = tmp_path / "run"
    assert main(["train", "--hp", "learning_rat=1e-4", "--total-timesteps", "64", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "--hp learning_rat" in err and "learning_rate" in err
    assert not out.exists()


def test_rllib_policy_paths_are_resolved_to_absolute(tmp_path, monkeypatch):
    # Ray reads a relative checkpoint path as a URI without a scheme: the CLI hands it an absolute one
    import uwb_env.agents.registry as registry

    seen = []
    monkeypatch.setattr(registry, "make_policy", lambda spec, *a: seen.append(spec))
    monkeypatch.chdir(tmp_path)
    assert check_policies(["rllib:runs/rllib/checkpoint", "fixed:10"]) == [
        f"rllib:{tmp_path.resolve()}/runs/rllib/checkpoint", "fixed:10"]
    assert seen[0] == f"rllib:{tmp_path.resolve()}/runs/rllib/checkpoint"


def test_train_help_names_the_rllib_backend_and_defaults(capsys):
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    out = capsys.readouterr().out
    assert "rllib" in out and "Ray RLlib" in out and "(default: 200000)" in out and "(default: ppo)" in out
@pytest.mark.parametrize(
    "argv, needle",
    [
        (["evaluate", "--policies", "learned:nope.zip", "--seeds", "1"], "nope.zip"),
        (["evaluate", "--config", "missing.yml", "--seeds", "1"], "--config missing.yml"),
        (["evaluate", "--policies", "fixed:abc", "--seeds", "1"], "fixed:abc"),
        (["train", "--hp", "learning_rat=1e-4", "--total-timesteps", "64"], "learning_rat"),
    ],
)
def test_cli_mistakes_print_one_line_naming_the_argument_and_exit_2(argv, needle, tmp_path, capsys, monkeypatch):
    from uwb_env.cli import main

    monkeypatch.chdir(tmp_path)
    if argv[0] == "train":
        argv = [*argv, "--out", str(tmp_path / "run")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err
    assert not (tmp_path / "run").exists()  # nothing half-written
