"""``zagv map build|eval|bench|localize`` runs ``python -m services.localization.slam`` as a subprocess: the arguments
pass through unchanged (``--help`` included), its output is relayed and its exit code kept."""

from __future__ import annotations

from services.cli.main import main


def test_help_is_the_slam_entry_points(capsys):
    assert main(["map", "build", "--help"]) == 0
    out = capsys.readouterr().out
    assert "usage: python -m services.localization.slam build" in out and "--max-scans" in out


def test_errors_and_exit_code_pass_through(capsys, tmp_path):
    assert main(["map", "eval", str(tmp_path / "log.clf")]) == 2  # argparse: RELATIONS is missing
    assert "the following arguments are required: relations" in capsys.readouterr().err
    missing = tmp_path / "none.clf"
    code = main(["map", "build", str(missing), "--out", str(tmp_path / "out"), "--max-scans", "5"])
    captured = capsys.readouterr()
    assert code != 0 and str(missing) in captured.err, captured


def test_map_info_stays_in_process(tmp_path, capsys):
    assert main(["map", "info", str(tmp_path / "none.yaml")]) == 2
    assert "zagv map info" in capsys.readouterr().err
