"""A sweep's progress: one bar with the rate and the time left on a terminal, plain lines in a
log (one per point for a small sweep, else one every LINE_EVERY_S), and a line for every point
that failed or was lost either way, so that a 1000-point run neither floods a log nor hides a
failure."""

from __future__ import annotations

import sys
import time
from collections import Counter
from collections.abc import Callable, Mapping
from typing import Any, TextIO

from aperture_fab.sweep.results import summary_line

__all__ = ["Progress", "duration"]

#: In a log: a status line this often (seconds) when points are not printed one by one.
LINE_EVERY_S = 30.0
#: In a log: up to this many points, one line per finished point.
PER_POINT_LINES_MAX = 100
#: On a terminal: the bar is redrawn at most this often (seconds).
REDRAW_S = 0.5
BAR_WIDTH = 24
SECONDS_PER = (("d", 86400), ("h", 3600), ("min", 60), ("s", 1))


def duration(seconds: float) -> str:
    """'2 h 05 min', '3 min 20 s', '12 s'."""
    seconds = max(0.0, seconds)
    for n, (unit, size) in enumerate(SECONDS_PER[:-1]):
        if seconds >= size:
            small_unit, small = SECONDS_PER[n + 1]
            return f"{int(seconds // size)} {unit} {int(seconds % size // small):02d} {small_unit}"
    return f"{seconds:.0f} s"


class Progress:
    """Counts finished points and says so. log: where lines go; terminal: draw a bar on
    `stream` (a TTY) instead of status lines."""

    def __init__(self, total: int, log: Callable[[str], None], terminal: bool = False,
                 stream: TextIO | None = None, clock: Callable[[], float] = time.monotonic
                 ) -> None:
        self.total, self.log, self.terminal = total, log, terminal
        self.stream = stream if stream is not None else sys.stderr
        self.clock = clock
        self.counts: Counter[str] = Counter()
        self.start = self.last = clock()
        self.drawn = False

    def add(self, more: int) -> None:
        """A search asks for more points as it goes."""
        self.total += more

    @property
    def finished(self) -> int:
        return sum(self.counts.values())

    def status(self) -> str:
        """'12/40 points (11 ok, 1 failed), 3.1 per min, about 2 min 35 s left'."""
        elapsed = self.clock() - self.start
        parts = ", ".join(f"{n} {s}" for s, n in sorted(self.counts.items()))
        text = f"{self.finished}/{self.total} points ({parts or 'none finished yet'})"
        if self.finished and elapsed > 0:
            rate = self.finished / elapsed
            left = duration((self.total - self.finished) / rate)
            text += f", {rate * 60:.3g} per min, about {left} left"
        return text

    def done(self, record: Mapping[str, Any], label: str) -> None:
        """A point finished (any status)."""
        self.counts[str(record["status"])] += 1
        line = f"[{self.finished}/{self.total}] {summary_line(record, label)}"
        if record["status"] != "ok" or (not self.terminal and self.total <= PER_POINT_LINES_MAX):
            self._line(line)
        self.tick(force=self.terminal)

    def tick(self, force: bool = False) -> None:
        """Redraw the bar (terminal) or print a status line when one is due (log)."""
        now = self.clock()
        if self.terminal:
            if force or now - self.last >= REDRAW_S:
                share = self.finished / self.total if self.total else 1.0
                filled = int(BAR_WIDTH * share)
                self.stream.write(f"\r[{'#' * filled}{'.' * (BAR_WIDTH - filled)}] "
                                  f"{self.status()}\x1b[K")
                self.stream.flush()
                self.drawn, self.last = True, now
        elif self.total > PER_POINT_LINES_MAX and now - self.last >= LINE_EVERY_S:
            self.log(self.status())
            self.last = now

    def _line(self, text: str) -> None:
        if self.terminal and self.drawn:
            self.stream.write("\r\x1b[K")  # the line goes above the bar, which is redrawn
            self.stream.flush()
        self.log(text)

    def close(self) -> None:
        if self.terminal and self.drawn:
            self.stream.write("\n")
            self.stream.flush()
