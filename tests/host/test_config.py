"""The oibar configuration file (host/oibar/config.py): TOML values through the same argparse
rules as the command line, the command line over the file, every mistake a one-line error with
exit status 2, and the search path."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import pytest

from oibar import cli, config

ROOT = Path(__file__).resolve().parents[2]
# What tests/conftest.py set for the session, before this module's fixture clears it per test.
SESSION_OIBAR_CONFIG = os.environ.get("OIBAR_CONFIG")


@pytest.fixture(autouse=True)
def no_user_config(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """No configuration of the machine running the tests leaks in."""
    monkeypatch.delenv("OIBAR_CONFIG", raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    monkeypatch.setattr(config, "SYSTEM_CONFIG", tmp_path / "etc" / "oibar.toml")


def parse(argv: list[str], text: str | None, tmp_path: Path) -> argparse.Namespace:
    """argv parsed as `oibar` does, with ``text`` as the configuration file."""
    parser = cli.build_parser()
    if text is not None:
        path = tmp_path / "oibar.toml"
        path.write_text(text)
        config.apply(parser, path)
    return parser.parse_args(argv)


def run_main(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    rc = cli.main(argv)
    return rc, capsys.readouterr().err


def test_file_values_are_defaults_and_the_command_line_wins(tmp_path: Path) -> None:
    text = """
verbose = 1
[nav]
camera = "/dev/video2"
port = "/dev/ttyACM0"
rate-hz = 5
threads = 3
record-frames = true
calibration = "cams/front.yaml"
[link]
port = "loop://"
seconds = 0
"""
    a = parse(["nav"], text, tmp_path)  # --camera and --port are required, the file gives them
    assert (a.camera, a.port, a.rate_hz, a.threads, a.record_frames) == (
        "/dev/video2",
        "/dev/ttyACM0",
        5.0,
        3,
        True,
    )
    assert a.verbose == 1
    assert a.calibration == tmp_path / "cams" / "front.yaml"  # relative to the file's folder
    assert a.camera_dead_s == 4.0  # not in the file: the built-in default
    b = parse(["nav", "--rate-hz", "8", "--camera", "1"], text, tmp_path)
    assert (b.rate_hz, b.camera, b.port) == (8.0, "1", "/dev/ttyACM0")
    c = parse(["link"], text, tmp_path)
    assert (c.port, c.seconds) == ("loop://", 0.0)


def test_option_with_an_optional_value(tmp_path: Path) -> None:
    """`oibar nav --live [HOST:]PORT`: true is the option alone, false its absence, a value (a
    port, or an address as a string) goes through its type, and the command line still wins."""
    base = ["nav", "--camera", "0", "--port", "none"]

    def live(argv: list[str]) -> object:
        return cli.build_parser().parse_args([*base, *argv]).live

    assert parse(base, "[nav]\nlive = true\n", tmp_path).live == live(["--live"]) == ("127.0.0.1", 8765)
    assert parse(base, "[nav]\nlive = false\n", tmp_path).live is None
    assert parse(base, "[nav]\nlive = 9100\n", tmp_path).live == live(["--live", "9100"])
    text = '[nav]\nlive = "0.0.0.0:9100"\n'
    assert parse(base, text, tmp_path).live == live(["--live", "0.0.0.0:9100"]) == ("0.0.0.0", 9100)
    assert parse(base, '[nav]\nlive = "127.0.0.1:8765"\n', tmp_path).live == ("127.0.0.1", 8765)
    assert parse([*base, "--live", "9200"], text, tmp_path).live == ("127.0.0.1", 9200)
    assert parse([*base, "--live"], text, tmp_path).live == ("127.0.0.1", 8765)


def test_required_options_still_required_without_the_file(tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as exc:
        parse(["nav"], "[nav]\nrate-hz = 5\n", tmp_path)
    assert exc.value.code == 2


def test_nested_subcommands_and_exclusive_groups(tmp_path: Path) -> None:
    text = '[calibrate-camera]\nchessboard = "9x6"\nsquare-mm = 25\nout = "cam.yaml"\n'
    a = parse(["calibrate-camera", "shots/"], text, tmp_path)
    assert a.chessboard == (9, 6) and a.square_mm == 25.0 and a.out == tmp_path / "cam.yaml"
    c = parse(
        ["calib", "estimate"] + _estimate_inputs(),
        '[calib.estimate]\npattern = "p.json"\nhousing-body = "cam"\ntarget-body = "tv"\nout = "c.json"\n',
        tmp_path,
    )
    assert c.pattern == tmp_path / "p.json" and c.housing_body == "cam"


def test_the_command_line_wins_within_an_exclusive_group(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The file sets one of two options that exclude each other; the command line gives the
    other: the command line's is taken and the file's dropped, as if the file had not set it."""
    text = '[calibrate-camera]\nchessboard = "9x6"\nsquare-mm = 25\nout = "cam.yaml"\n'
    a = parse(["calibrate-camera", "shots/", "--charuco", "7x5"], text, tmp_path)
    assert a.charuco == (7, 5) and a.chessboard is None
    assert a.square_mm == 25.0  # the file's other values stay
    b = parse(["calibrate-camera", "shots/"], text, tmp_path)
    assert b.chessboard == (9, 6) and b.charuco is None
    c = parse(["calibrate-camera", "shots/", "--chessboard", "8x5"], text, tmp_path)
    assert c.chessboard == (8, 5) and c.charuco is None
    with pytest.raises(SystemExit) as exc:  # both on the command line: still argparse's error
        parse(["calibrate-camera", "shots/", "--chessboard", "8x5", "--charuco", "7x5"], text, tmp_path)
    assert exc.value.code == 2 and "not allowed with" in capsys.readouterr().err
    with pytest.raises(config.ConfigError, match="chessboard and charuco exclude each other"):
        parse(["calibrate-camera", "shots/"], text + 'charuco = "7x5"\n', tmp_path)


def _estimate_inputs() -> list[str]:
    """Whatever `oibar calib estimate` needs besides the options the test gives in the file."""
    parser = cli.build_parser()
    estimate = config.subparsers(config.subparsers(parser)["calib"])["estimate"]
    out: list[str] = []
    for action in estimate._actions:
        if action.required and action.option_strings and action.dest not in (
            "pattern", "housing_body", "target_body", "out"
        ):  # fmt: skip
            out += [action.option_strings[-1], "x"]
        elif not action.option_strings and action.nargs not in ("*", "?"):
            out.append("x")
    return out


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[nav]\nrate-hz = 0\n", "[nav] rate-hz = 0: '0' is out of range: must be > 0 and <= 100"),
        ("[nav]\nrate-hz = 101\n", "'101' is out of range: must be > 0 and <= 100"),
        ("[nav]\nthreads = 2.5\n", "[nav] threads = 2.5: '2.5' is not an integer"),
        ("[nav]\nrate-hz = nan\n", "is not a finite number"),
        ("[nav]\nrate_hz = 5\n", "unknown key 'rate_hz' in [nav] (did you mean 'rate-hz'?)"),
        ("[nav]\nratehz = 5\n", "unknown key 'ratehz' in [nav]"),
        ("[navigate]\nport = 'x'\n", "unknown key 'navigate' in top level"),
        ("nav = 3\n", "'nav' is a subcommand: make it a table, [nav]"),
        ("[nav]\nrecord-frames = 'yes'\n", "[nav] record-frames = 'yes': must be true or false"),
        ("[nav]\ncamera = true\n", "[nav] camera = True: must be a string or a number"),
        ("[nav]\ncamera = ''\n", "--camera must not be empty"),
        ("[pose]\nframes = ['a.png']\n", "a positional argument: give it on the command line"),
        ("[link]\ncommand = 'NOOP'\n", "[link] command = 'NOOP': must be a list of values"),
        ("[nav]\nlive = 'h:70000'\n", "[nav] live = 'h:70000': --live 'h:70000': expected PORT, HOST:PORT"),
        ("[nav\n", "not valid TOML"),
    ],
)
def test_mistakes_are_one_line_errors_with_status_2(
    text: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    rc, err = run_main(["nav", "--config", str(path), "--camera", "0", "--port", "none"], capsys)
    assert rc == 2
    assert message in err, err
    assert err.startswith("oibar: error: configuration: ") and err.count("\n") == 1
    assert "Traceback" not in err


def test_same_rule_and_words_as_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["nav", "--camera", "0", "--port", "none", "--rate-hz", "0"])
    from_cli = capsys.readouterr().err
    path = tmp_path / "c.toml"
    path.write_text("[nav]\nrate-hz = 0\n")
    _, from_file = run_main(["nav", "--config", str(path)], capsys)
    rule = "'0' is out of range: must be > 0 and <= 100"
    assert rule in from_cli and rule in from_file


def test_the_test_session_reads_no_configuration_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """tests/conftest.py sets OIBAR_CONFIG=none for the whole session: a developer's own
    ~/.config/oibar/oibar.toml (or /etc/oibar/oibar.toml) cannot change what a test runs."""
    assert SESSION_OIBAR_CONFIG == "none"
    user = tmp_path / "xdg" / "oibar" / "oibar.toml"
    user.parent.mkdir(parents=True)
    user.write_text("[nav]\nrate-hz = 5\n")
    assert config.find_config(["nav"]) == user  # found when nothing says otherwise
    monkeypatch.setenv("OIBAR_CONFIG", SESSION_OIBAR_CONFIG)
    assert config.find_config(["nav"]) is None


def test_which_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert config.find_config([]) is None  # nothing anywhere: no file, no error
    system = tmp_path / "etc" / "oibar.toml"
    system.parent.mkdir()
    system.write_text("")
    assert config.find_config(["nav"]) == system
    user = tmp_path / "xdg" / "oibar" / "oibar.toml"
    user.parent.mkdir(parents=True)
    user.write_text("")
    assert config.find_config(["nav"]) == user  # the user's before the system's
    env = tmp_path / "env.toml"
    env.write_text("")
    monkeypatch.setenv("OIBAR_CONFIG", str(env))
    assert config.find_config(["nav"]) == env
    given = tmp_path / "given.toml"
    given.write_text("")
    assert config.find_config(["nav", "--config", str(given)]) == given
    assert config.find_config(["--config=" + str(given), "nav"]) == given
    assert config.find_config(["nav", "--config", "none"]) is None
    monkeypatch.setenv("OIBAR_CONFIG", "none")
    assert config.find_config(["nav"]) is None
    with pytest.raises(config.ConfigError, match="no such file"):
        config.find_config(["nav", "--config", str(tmp_path / "missing.toml")])


def test_an_abbreviated_option_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """argparse would take --conf for --config after the file search missed it: refused."""
    path = tmp_path / "c.toml"
    path.write_text("[nav]\nrate-hz = 0\n")
    with pytest.raises(SystemExit) as exc:  # argparse's usage error, as for any bad argument
        cli.main(["nav", "--camera", "0", "--port", "none", "--conf", str(path)])
    assert exc.value.code == 2 and "write --config in full" in capsys.readouterr().err


def test_default_location_is_read(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    user = tmp_path / "xdg" / "oibar" / "oibar.toml"
    user.parent.mkdir(parents=True)
    user.write_text("[nav]\nrate-hz = -1\n")
    rc, err = run_main(["nav", "--camera", "0", "--port", "none"], capsys)
    assert rc == 2 and str(user) in err
    rc, _ = run_main(
        ["nav", "--config", "none", "--camera", "0", "--port", "none", "--model", "/nonexistent"], capsys
    )
    assert rc == 2  # the file is skipped; what fails now is the model


def test_the_shipped_template_is_valid(tmp_path: Path) -> None:
    parser = cli.build_parser()
    config.apply(parser, ROOT / "deploy" / "oibar.toml")
    a = parser.parse_args(["nav"])
    assert (a.camera, a.port, a.rate_hz) == ("/dev/video0", "/dev/ttyACM0", 10.0)
