"""Progress on a terminal: a bar with rate and ETA; silent when not a terminal or --quiet."""
from __future__ import annotations

import sys
import time

BAR_WIDTH = 28  # characters


class Progress:
    def __init__(self, label: str, total: int, enabled: bool | None = None, unit: str = "frames"):
        self.label, self.total, self.unit = label, max(int(total), 1), unit
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self.start = time.monotonic()

    def __call__(self, done: int, total: int | None = None, note: str = "") -> None:
        if not self.enabled:
            return
        total = total or self.total
        elapsed = time.monotonic() - self.start
        rate = done / elapsed if elapsed > 0 else 0.0
        eta = (total - done) / rate if rate > 0 else 0.0
        filled = int(BAR_WIDTH * done / total)
        bar = "#" * filled + "-" * (BAR_WIDTH - filled)
        sys.stderr.write(f"\r{self.label} [{bar}] {done}/{total} {self.unit} {rate:5.1f}/s ETA {eta:5.1f}s {note}")
        if done >= total:
            sys.stderr.write("\n")
        sys.stderr.flush()
