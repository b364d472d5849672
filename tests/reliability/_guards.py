"""Guards shared by the reliability tests."""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator


@contextlib.contextmanager
def no_hang(seconds: float = 30.0) -> Iterator[None]:
    """Fail (a TimeoutError) instead of hanging when the body runs longer than ``seconds`` (wall clock,
    SIGALRM: the main thread of a POSIX process)."""

    def on_alarm(signum, frame):
        raise TimeoutError(f"ran longer than {seconds} s")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
