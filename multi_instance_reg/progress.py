"""A one-line progress bar for long runs over frames, images or bags."""
from __future__ import annotations

import sys
import time


class Progress:
    """A one-line progress bar on stderr (drawn only when stderr is a terminal): done of
    total, the rate and the time left."""

    def __init__(self, total: int, enabled: bool = True, unit: str = "frames", width: int = 30):
        self.total, self.width, self.unit = max(total, 1), width, unit
        self.enabled = enabled and sys.stderr.isatty()
        self.t0 = time.perf_counter()

    def update(self, done: int, extra: str = "", counted_from: int = 0) -> None:
        """``counted_from``: tasks already done before this run started (a resumed run):
        they count towards the bar but not the rate."""
        if not self.enabled:
            return
        frac = min(done / self.total, 1.0)
        bar = "#" * int(frac * self.width) + "." * (self.width - int(frac * self.width))
        rate = (done - counted_from) / max(time.perf_counter() - self.t0, 1e-9)
        left = f" {_duration((self.total - done) / rate)} left" if rate > 0 and done < self.total else ""
        sys.stderr.write(f"\r[{bar}] {done}/{self.total} {self.unit} {rate:.2f}/s{left} {extra}")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")
            sys.stderr.flush()


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"
