"""Errors a user can act on. The CLI prints their message on one line and exits with 2."""
from __future__ import annotations

import sys


def print_warning(line: str) -> None:
    """A warning the user should see but that does not stop the run: one line on stderr."""
    print(f"warning: {line}", file=sys.stderr)


class UserError(Exception):
    """Bad input: a missing or corrupt file, a wrong size, a bad option. Message names the culprit."""


class InputFileError(UserError):
    """A file that cannot be read or does not hold what it should."""

    def __init__(self, path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")
