import json

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
