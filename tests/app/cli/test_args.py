"""What a refused argument says (app.cli.args): the command it was given to and its help,
the close match of a misspelt option, command or choice; the port types."""

from __future__ import annotations

import argparse

import pytest

from tests.support import run_cli
from trifuse.app.cli import build_parser
from trifuse.app.cli.args import listen_port, port_number, share_of_a_core

SUGGESTIONS = [
    (
        ["calibrate", "--ouy", "x", "cap"],
        "trifuse calibrate: unknown option --ouy; did you mean --out?",
    ),
    (
        ["calibrate", "cap", "--out", "r.yaml", "--reprot", "r.json"],
        "trifuse calibrate: unknown option --reprot; did you mean --report?",
    ),
    (
        ["calibrate", "cap", "--out=r.yaml", "--reprot=r.json"],
        "trifuse calibrate: unknown option --reprot; did you mean --report?",
    ),
    (["serve", "--prot", "8001"], "trifuse serve: unknown option --prot; did you mean --port?"),
    (
        ["rig", "export", "r.yaml", "--fromat", "ros", "--out", "d"],
        "trifuse rig export: unknown option --fromat; did you mean --format?",
    ),
    (["--verison"], "trifuse: unknown option --verison; did you mean --version?"),
    (
        ["calbrate", "cap"],
        "trifuse: argument COMMAND: invalid choice: 'calbrate', did you mean 'calibrate'? "
        "(choose from 'simulate', ",
    ),
    (
        ["rig", "exprt"],
        "trifuse rig: argument ACTION: invalid choice: 'exprt', did you mean 'export'?",
    ),
    (
        ["record", "--source", "sim", "--out", "o.mcap", "--scenario", "survy"],
        "trifuse record: argument --scenario: invalid choice: 'survy', did you mean 'survey'? "
        "(choose from 'inspection', 'survey')",
    ),
    (
        ["calibrate", "cap", "--out", "r.yaml", "--ouy", "x", "--zzz"],
        "trifuse calibrate: unknown options --ouy (did you mean --out?), --zzz",
    ),
]


@pytest.mark.parametrize(("argv", "says"), SUGGESTIONS, ids=[" ".join(a) for a, _ in SUGGESTIONS])
def test_a_typo_gets_the_close_match_and_the_commands_help(
    argv: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = run_cli(argv, capsys)
    assert code == 2 and out == ""
    assert err.startswith(says), err
    assert len(err.strip().splitlines()) == 1
    command = says.split(":")[0]  # "trifuse calibrate", "trifuse rig export", "trifuse"
    assert err.rstrip().endswith(f"(see '{command} --help')"), err


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["calibrate", "cap", "--out", "r.yaml", "--frobnicate"], "unknown option --frobnicate"),
        (["bogus"], "invalid choice: 'bogus' (choose from"),
        (["calibrate", "cap", "--out", "r.yaml", "extra"], "unrecognized arguments: extra"),
    ],
)
def test_nothing_close_no_suggestion(
    argv: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, err = run_cli(argv, capsys)
    assert code == 2 and says in err and "did you mean" not in err
    assert len(err.strip().splitlines()) == 1


def test_what_argparse_takes_is_still_taken() -> None:
    """Abbreviations, ``--opt=value``, negative numbers and values after ``--`` are not
    taken for unknown options."""
    parser = build_parser()
    args = parser.parse_args(["calibrate", "cap", "--ou", "r.yaml", "--report=r.json"])
    assert (args.out, args.report) == ("r.yaml", "r.json")
    args = parser.parse_args(["analyze", "rig.yaml", "--tof-pixel=-1.5,2"])
    assert args.tof_pixel == [(-1.5, 2.0)]
    args = parser.parse_args(["record", "--source", "sim", "--out", "o", "--pose-hz", "-5"])
    assert args.pose_hz == -5.0  # refused later, by the command, with its own message
    args = parser.parse_args(["map", "--out", "m.ply", "--", "-odd.mcap"])
    assert args.recordings == ["-odd.mcap"]


def test_an_ambiguous_abbreviation_is_argparses_message(capsys: pytest.CaptureFixture) -> None:
    code, _, err = run_cli(["calibrate", "cap", "--out", "r.yaml", "--re", "x"], capsys)
    assert code == 2
    assert "ambiguous option: --re could match --report, --report-html, --reference" in err


def test_port_types() -> None:
    assert [listen_port(t) for t in ("0", "1", "8000", "65535")] == [0, 1, 8000, 65535]
    assert [port_number(t) for t in ("1", "65535")] == [1, 65535]
    for parse, text in [(listen_port, "-1"), (listen_port, "65536"), (port_number, "0")]:
        with pytest.raises(argparse.ArgumentTypeError, match=f"got {int(text)}$"):
            parse(text)
    with pytest.raises(argparse.ArgumentTypeError, match=r"expected a port number .* got 'abc'"):
        listen_port("abc")


def test_share_of_a_core() -> None:
    assert [share_of_a_core(t) for t in ("0.01", "0.5", "1")] == [0.01, 0.5, 1.0]
    for text in ("0", "1.5", "nan", "x"):
        with pytest.raises(argparse.ArgumentTypeError, match=r"one core from 0\.01 to 1"):
            share_of_a_core(text)
    args = build_parser().parse_args(["serve", "--drift-share", "0.5"])
    assert args.drift_share == 0.5
    assert build_parser().parse_args(["serve"]).drift_share is None  # the watch's 0.1
