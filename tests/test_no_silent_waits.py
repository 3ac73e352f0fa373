"""No silent waits: a command that waits for a daemon or a peer says at once on stderr what
it waits for and how to stop it, then how long it has waited; the exit code and the one-line
error at the end stay. The commands run as a user runs them (``sinewatch ...`` processes)
against an endpoint where nothing listens."""

from __future__ import annotations

import queue
import subprocess
import threading
import time

import pytest
from conftest import sinewatch

from sinewatch.clients.session import free_loopback_port


class StderrLines:
    """A process's stderr, line by line, each with the time it arrived (a reader thread)."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.lines: queue.Queue[tuple[float, str | None]] = queue.Queue()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.put((time.monotonic(), line.rstrip("\n")))
        self.lines.put((time.monotonic(), None))

    def next(self, deadline: float) -> tuple[float, str | None]:
        """The next line, or fail once ``deadline`` (monotonic) has passed without one."""
        try:
            return self.lines.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            raise AssertionError("no line on stderr before the deadline") from None

    def rest(self) -> list[tuple[float, str]]:
        out = []
        while (item := self.lines.get(timeout=120))[1] is not None:
            out.append((item[0], item[1]))
        return out


def _run(*args: str) -> tuple[float, StderrLines]:
    started = time.monotonic()
    proc = subprocess.Popen(sinewatch(*args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    return started, StderrLines(proc)


def test_tail_says_at_once_what_it_waits_for_then_how_long_then_the_error():
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"  # nothing listens there
    started, err = _run("tail", "--connect", endpoint, "--wait", "6")
    # "at once" is judged against the wait itself (the error comes more than 5 s after the
    # first line, below), not against a wall-clock deadline that a loaded machine can miss
    at, first = err.next(started + 120)
    assert first == f"tail: waiting for a Zenoh router or daemon at {endpoint} (up to 6 s; Ctrl-C to stop)"
    rest = err.rest()
    assert err.proc.wait(timeout=120) == 2
    assert [line for _, line in rest][:1] == [
        f"tail: still waiting for a Zenoh router or daemon at {endpoint} (5 s of 6 s)"
    ]
    assert rest[-1][1].startswith("sinewatch: error: could not open the Zenoh session") and len(rest) == 2
    assert rest[-1][0] - at > 5.0  # said as the wait began, not as it ended


@pytest.mark.parametrize(
    ("command", "extra"), [("feed", ["--duration", "1"]), ("status", []), ("tail", ["sinewatch/est/**"])]
)
def test_every_command_that_connects_says_what_it_waits_for(command, extra):
    """The first line is what it waits for, said as the wait begins: the one-line error comes
    the whole wait (3 s) later."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    started, err = _run(command, *extra, "--connect", endpoint, "--wait", "3")
    at, first = err.next(started + 120)
    assert first == f"{command}: waiting for a Zenoh router or daemon at {endpoint} (up to 3 s; Ctrl-C to stop)"
    rest = err.rest()
    assert err.proc.wait(timeout=120) == 2
    assert len(rest) == 1 and rest[0][1].startswith("sinewatch: error: could not open the Zenoh session")
    assert rest[0][0] - at > 2.5
