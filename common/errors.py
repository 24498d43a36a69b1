"""Errors a user can act on. The CLI prints their message on one line and exits with 2."""
from __future__ import annotations

import json
import math
import sys
from typing import Callable

SHOWN_CHARS = 40  # of a bad value quoted in a message: enough to recognise it, short enough for one line


WARNING_PREFIX = "warning: "  # how a warning line starts: mocap run finds its steps' warnings by it


def print_warning(line: str) -> None:
    """A warning the user should see but that does not stop the run: one line on stderr."""
    print(f"{WARNING_PREFIX}{line}", file=sys.stderr)


class UserError(Exception):
    """Bad input: a missing or corrupt file, a wrong size, a bad option. Message names the culprit."""


class InputFileError(UserError):
    """A file that cannot be read or does not hold what it should."""

    def __init__(self, path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


def shown(value) -> str:
    """A value as a message quotes it: its repr, cut to SHOWN_CHARS."""
    text = repr(value)
    return text if len(text) <= SHOWN_CHARS else text[:SHOWN_CHARS - 3] + "..."


def _kind(value) -> str:
    """What a parsed JSON / TOML / YAML value is, in the words of a message."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (int, float)):
        return f"the number {shown(value)}"
    if isinstance(value, str):
        return f"the text {shown(value)}"
    if isinstance(value, (list, tuple)):
        return f"a list of {len(value)}"
    if isinstance(value, dict):
        return "an object"
    return shown(value)


def _field_input_error(path: str, where: str, problem: str) -> UserError:
    return InputFileError(path, f"{where}: {problem}" if where else problem)


class FieldChecks:
    """Type and range checks of a parsed document's fields (JSON, TOML, YAML), shared by every
    reader: a failure is one error naming the file, the line of line-based files and the field,
    e.g. ``truth.jsonl: line 3: joints.pelvis: expected a list of 3 numbers, got a list of 2``.

    error(path, where, problem) makes the exception, ``where`` being "line N: FIELD", "FIELD",
    or "" for the whole file: InputFileError by default; the calibration readers pass one making
    CalibrationError.
    """

    def __init__(self, path, line: int | None = None,
                 error: Callable[[str, str, str], UserError] = _field_input_error):
        self.path = str(path)
        self.line = line
        self._error = error

    def error(self, field: str, problem: str, line: int | None = None) -> UserError:
        line = self.line if line is None else line
        where = ": ".join(part for part in ("" if line is None else f"line {line}", field) if part)
        return self._error(self.path, where, problem)

    def read(self) -> bytes:
        """The file's bytes."""
        try:
            with open(self.path, "rb") as fh:
                return fh.read()
        except FileNotFoundError:
            raise self.error("", "missing") from None
        except IsADirectoryError:
            raise self.error("", "a folder, expected a file") from None
        except OSError as exc:
            raise self.error("", f"cannot read ({exc.strerror or exc})") from None

    def decode(self, data: bytes) -> str:
        """A text file's bytes as text: UTF-8, with or without a byte-order mark."""
        try:
            return data.decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            line = (self.line or 1) + data.count(b"\n", 0, exc.start)
            raise self.error("", f"not UTF-8 text (byte 0x{data[exc.start]:02x})", line) from None

    def parse_json(self, data: bytes):
        """A JSON document (a file, or one line of a JSON-lines file) from its bytes."""
        try:
            return json.loads(self.decode(data))
        except json.JSONDecodeError as exc:
            raise self.error("", f"not valid JSON ({exc})") from None
        except RecursionError:  # json gives up on very deep nesting this way
            raise self.error("", "not valid JSON (nested too deeply)") from None

    def object(self, value, field: str) -> dict:
        if not isinstance(value, dict):
            raise self.error(field, f"expected an object {{...}}, got {_kind(value)}")
        return value

    def items(self, value, field: str) -> list:
        if not isinstance(value, list):
            raise self.error(field, f"expected a list [...], got {_kind(value)}")
        return value

    def text(self, value, field: str) -> str:
        if not isinstance(value, str) or not value:
            raise self.error(field, f"expected a non-empty text in quotes, got {_kind(value)}")
        return value

    def flag(self, value, field: str) -> bool:
        if not isinstance(value, bool):
            raise self.error(field, f"expected true or false, got {_kind(value)}")
        return value

    def number(self, value, field: str, minimum: float | None = None, exclusive_minimum: bool = False) -> float:
        """A finite number (not true / false), >= ``minimum`` (> with ``exclusive_minimum``)."""
        wanted = "a finite number" + ("" if minimum is None else f" {'>' if exclusive_minimum else '>='} {minimum:g}")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(field, f"expected {wanted}, got {_kind(value)}")
        try:
            number = float(value)
        except OverflowError:  # an integer beyond any float
            raise self.error(field, f"expected {wanted}, got {_kind(value)}") from None
        if not math.isfinite(number) or (minimum is not None and (number <= minimum if exclusive_minimum
                                                                  else number < minimum)):
            raise self.error(field, f"expected {wanted}, got {_kind(value)}")
        return number

    def whole(self, value, field: str, minimum: int | None = None) -> int:
        """A whole number (3 or 3.0; not true / false) >= ``minimum``."""
        wanted = "a whole number" + ("" if minimum is None else f" >= {minimum}")
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int) or (minimum is not None and value < minimum):
            raise self.error(field, f"expected {wanted}, got {_kind(value)}")
        return value

    def numbers(self, value, field: str, length: int) -> list[float]:
        """A list of ``length`` finite numbers (a vector)."""
        if not isinstance(value, list) or len(value) != length:
            raise self.error(field, f"expected a list of {length} numbers, got {_kind(value)}")
        return [self.number(x, f"{field}[{i}]") for i, x in enumerate(value)]
