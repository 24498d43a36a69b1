"""Checked argparse types: every numeric option says what range it takes.

argparse turns the ``ArgumentTypeError`` these raise into ``argument --NAME: MESSAGE``, and
``OneLineParser`` prints that as one line with exit 2, so ``--frames -1`` or ``--fov nan``
are refused before any work starts instead of meaning something surprising.
"""
from __future__ import annotations

import argparse
import math
import sys
from typing import Callable


class OneLineParser(argparse.ArgumentParser):
    """argparse with one-line errors: ``mocap fit: error: argument --frames: ...`` and exit 2
    (the usage text is what ``--help`` is for)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see {self.prog} --help)\n")

    def parse_known_args(self, args=None, namespace=None):
        # argparse turns the value of ``--opt=--`` into an empty list, which no type converts
        for arg in sys.argv[1:] if args is None else args:
            if isinstance(arg, str) and arg.startswith("--") and arg.endswith("=--"):
                self.error(f"argument {arg[:-3]}: expected a value, got '--'")
        return super().parse_known_args(args, namespace)


def one_line(text: str) -> str:
    """A message on one line (a path or a value may hold line breaks)."""
    return " ".join(str(text).split("\n")).replace("\r", " ")


def count(minimum: int = 0, maximum: int | None = None) -> Callable[[str], int]:
    """An integer >= ``minimum`` (0: "none" allowed, 1: at least one), and <= ``maximum``."""
    wanted = f"an integer >= {minimum}" + (f" and <= {maximum}" if maximum is not None else "")

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text!r}") from None
        if value < minimum or (maximum is not None and value > maximum):
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {value}")
        return value

    parse.__name__ = f"count>={minimum}"
    return parse


def real(minimum: float | None = None, maximum: float | None = None, exclusive_minimum: bool = False
         ) -> Callable[[str], float]:
    """A finite float within [minimum, maximum] ((minimum, maximum] with ``exclusive_minimum``)."""
    low = "" if minimum is None else (f"> {minimum:g}" if exclusive_minimum else f">= {minimum:g}")
    high = "" if maximum is None else f"<= {maximum:g}"
    wanted = " and ".join(p for p in (low, high) if p)
    wanted = f"a finite number{' ' + wanted if wanted else ''}"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text}")
        if minimum is not None and (value <= minimum if exclusive_minimum else value < minimum):
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {value:g}")
        if maximum is not None and value > maximum:
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {value:g}")
        return value

    parse.__name__ = "number"
    return parse


def seconds(text: str) -> float:
    """A finite duration > 0 seconds (time-outs, intervals)."""
    return real(0.0, exclusive_minimum=True)(text)


def non_negative(text: str) -> float:
    """A finite number >= 0 (a weight, a range, a distance)."""
    return real(0.0)(text)


ADDRESS_SCHEMES = ("tcp", "ipc", "inproc")  # the ZeroMQ transports a cluster may use
MAX_PORT = 65535


def zmq_address(text: str) -> str:
    """A ZeroMQ endpoint: tcp://HOST:PORT (PORT 1-65535, or * for a free one when binding),
    ipc://PATH or inproc://NAME. ZeroMQ itself takes port 99999 as 34463 (modulo 2^16) and
    says only "Invalid argument" for an address without its scheme."""
    scheme, sep, rest = text.partition("://")
    if not sep or scheme not in ADDRESS_SCHEMES:
        raise argparse.ArgumentTypeError(f"expected tcp://HOST:PORT (or ipc://PATH), got {text!r}")
    if scheme == "tcp":
        host, colon, port = rest.rpartition(":")
        if not colon or not host:
            raise argparse.ArgumentTypeError(f"expected tcp://HOST:PORT, got {text!r}")
        if port != "*" and not (port.isdigit() and 1 <= int(port) <= MAX_PORT):
            raise argparse.ArgumentTypeError(f"{text}: the port must be 1-{MAX_PORT}, got {port!r}")
    elif not rest:
        raise argparse.ArgumentTypeError(f"expected {scheme}://NAME, got {text!r}")
    return text
