"""What ``mocap --help`` and each command's ``--help`` say: every option explained, and lists
made from what is registered, so that they cannot drift from it."""
from __future__ import annotations

import argparse

import pytest

from server.cli import build_parser

pytestmark = pytest.mark.timeout(60)


def commands(parser: argparse.ArgumentParser, name: str):
    """(name, parser) of ``parser`` and of every (sub)command below it: "mocap calib convert"'s too."""
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                yield from commands(sub, f"{name} {sub_name}")


def test_every_option_of_every_command_says_what_it_does():
    from client.__main__ import build_parser as client_parser

    unexplained = [f"{name} {action.option_strings[0] if action.option_strings else action.dest}"
                   for parser, prog in ((build_parser(), "mocap"), (client_parser(), "mocap client"))
                   for name, command in commands(parser, prog)
                   for action in command._actions
                   if not isinstance(action, (argparse._HelpAction, argparse._SubParsersAction))
                   and action.help != argparse.SUPPRESS and not (action.help or "").strip()]
    assert not unexplained


def test_mocap_help_lists_every_bench(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--help"])
    listed = " ".join(capsys.readouterr().out.split())  # argparse wraps the line
    bench = dict(commands(build_parser(), "mocap"))["mocap bench"]
    names = next(a for a in bench._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert {"accuracy", "init", "all"} <= set(names)
    assert f"bench benchmarks ({', '.join(names)})" in listed
