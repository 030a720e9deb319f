import json

import pytest

from uwb_env.cli import main


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
