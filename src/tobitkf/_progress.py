"""Progress lines of long commands that stay readable in a log file.

A rich progress bar draws on a terminal only; written to a log or a CI console it shows nothing for as
long as the work lasts. :class:`Heartbeat` prints a line when a task starts, a line at least every
``every`` seconds while it runs (the fraction done and the latest step the task named) and a line when it
ends, with its time, to a stream (stderr by default), whether or not the stream is a terminal.
"""

from __future__ import annotations

import sys
import threading
import time
from typing import TextIO

__all__ = ["Heartbeat", "format_seconds", "plural"]


def plural(count: int, word: str, words: str | None = None) -> str:
    """``"1 kernel"``, ``"2 kernels"``, ``"0 kernels"``: the count and the word in the number it needs
    (``words``, default ``word + "s"``, for any count other than one)."""
    return f"{count} {word if count == 1 else (words if words is not None else word + 's')}"


def format_seconds(seconds: float) -> str:
    """``"4.2 s"``, ``"3 min 05 s"``, ``"1 h 02 min"``."""
    s = max(float(seconds), 0.0)
    if s < 60:
        return f"{s:.1f} s"
    if s < 3600:
        m, r = divmod(int(round(s)), 60)
        return f"{m} min {r:02d} s"
    h, r = divmod(int(round(s)), 3600)
    return f"{h} h {r // 60:02d} min"


class Heartbeat:
    """Lines about one running task: started, progress every ``every`` seconds, done (with its time).

    Use as a context manager around the task; call the instance as the task's progress callback,
    ``beat(fraction)`` or ``beat(fraction, "what it is doing")``. The periodic line comes from a
    daemon thread, so it appears even while the task sits in a long compiled call.

    Parameters
    ----------
    name : str
        The task's name, the first word of every line.
    every : float, default 30
        Seconds between progress lines; ``0`` or less: no periodic lines (start and end only).
    stream : text stream, default ``sys.stderr``
    prefix : str
        Put before the name on the start and end lines (e.g. ``"[3/29] "``).
    announce : bool, default True
        Print the start line, and a line when the task stops on an error. False (one task the user
        named): only the progress lines and the end line on success, so that an error stays the one
        line the caller prints.
    """

    def __init__(
        self,
        name: str,
        *,
        every: float = 30.0,
        stream: TextIO | None = None,
        prefix: str = "",
        announce: bool = True,
    ) -> None:
        self.name = name
        self.announce = announce
        self.every = float(every)
        self.stream = stream
        self.prefix = prefix
        self.fraction = 0.0
        self.note = ""
        self.elapsed = 0.0
        self._t0 = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    def _write(self, line: str) -> None:
        stream = self.stream if self.stream is not None else sys.stderr
        with self._lock:
            try:
                stream.write(line + "\n")
                stream.flush()
            except (OSError, ValueError):  # a closed or broken stream must not stop the work
                pass

    def __call__(self, fraction: float, note: str | None = None) -> None:
        """Record the task's progress (a fraction in [0, 1]) and, optionally, what it is doing."""
        try:
            f = float(fraction)
        except (TypeError, ValueError):
            return
        self.fraction = min(max(f, 0.0), 1.0) if f == f else self.fraction
        if note is not None:
            self.note = str(note)

    def line(self) -> str:
        """The periodic line: name, percent done, the latest note, time so far."""
        what = f", {self.note}" if self.note else ""
        return f"  {self.name}: {self.fraction:.0%}{what} ({format_seconds(time.perf_counter() - self._t0)})"

    def _run(self) -> None:
        while not self._stop.wait(self.every):
            self._write(self.line())

    def __enter__(self) -> Heartbeat:
        self._t0 = time.perf_counter()
        if self.announce:
            self._write(f"{self.prefix}{self.name}: started")
        if self.every > 0:
            self._thread = threading.Thread(target=self._run, name=f"heartbeat-{self.name}", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.elapsed = time.perf_counter() - self._t0
        if exc_type is None:
            self._write(f"{self.prefix}{self.name}: done in {format_seconds(self.elapsed)}")
        elif self.announce:
            self._write(f"{self.prefix}{self.name}: stopped ({exc_type.__name__}) in {format_seconds(self.elapsed)}")
