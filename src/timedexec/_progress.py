"""Progress with an ETA on stderr (status never goes to stdout)."""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ["Progress"]


class Progress:
    """A throttled progress line: ``label  1,234/33,500 (3.7 %)  12.3 s  ETA 4 min``.

    On a terminal the line is redrawn in place; otherwise a line is printed at most every
    ``interval_s`` seconds (logs stay short). ``enabled=False`` makes it silent.
    """

    def __init__(
        self,
        total: int,
        label: str,
        *,
        stream: TextIO | None = None,
        enabled: bool = True,
        interval_s: float = 2.0,
    ) -> None:
        self.total = max(int(total), 0)
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.done = 0
        self._start = time.monotonic()
        self._last = -1e9
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval_s = 0.2 if self._tty else interval_s

    def update(self, n: int = 1) -> None:
        """Count ``n`` more units done."""
        self.done += n
        now = time.monotonic()
        if self.enabled and (now - self._last >= self.interval_s or self.done >= self.total):
            self._last = now
            self._draw(now)

    def _draw(self, now: float) -> None:
        elapsed = now - self._start
        frac = self.done / self.total if self.total else 1.0
        eta = elapsed * (1 - frac) / frac if frac > 0 else float("nan")
        eta_text = _duration(eta) if eta == eta else "?"
        line = (
            f"{self.label}  {self.done:,}/{self.total:,} ({100 * frac:.1f} %)  "
            f"{_duration(elapsed)}  ETA {eta_text}"
        )
        end = "\r" if self._tty and self.done < self.total else "\n"
        print(line, end=end, file=self.stream, flush=True)

    def close(self) -> None:
        """Finish the line."""
        if self.enabled and self._tty and self.done < self.total:
            print(file=self.stream, flush=True)


def _duration(seconds: float) -> str:
    if seconds < 60:
        return f"{seconds:.1f} s"
    if seconds < 3600:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"
