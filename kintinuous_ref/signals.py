"""Signals that end a command: SIGINT, SIGTERM and SIGHUP all raise `Interrupted` (a
KeyboardInterrupt) in the main thread while `handle_signals` is in force, so that a run ends
the way Ctrl-C ends it and keeps its work (program/reconstruct.py). Standard library only: the
command line imports it before anything heavy."""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator
from typing import Any


class Interrupted(KeyboardInterrupt):
    """A signal that ends the command: SIGINT, SIGTERM or SIGHUP. `message` (when set) says
    what was kept."""

    def __init__(self, signal_name: str = "SIGINT", message: str = "") -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name
        self.message = message

    @property
    def exit_status(self) -> int:
        return 128 + int(getattr(signal, self.signal_name, signal.SIGINT))


def _raise_interrupted(number: int, _frame: Any) -> None:
    raise Interrupted(signal.Signals(number).name)


@contextlib.contextmanager
def handle_signals() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP raise Interrupted in the main thread while in force."""
    names = ("SIGINT", "SIGTERM", "SIGHUP")
    numbers = [getattr(signal, name) for name in names if hasattr(signal, name)]
    try:
        previous = {number: signal.signal(number, _raise_interrupted) for number in numbers}
    except ValueError:  # not the main thread: leave the handlers alone
        yield
        return
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
