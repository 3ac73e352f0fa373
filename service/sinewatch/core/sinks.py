"""Where the pipeline's outputs go: the :class:`Sink` protocol, :class:`NullSink` to
subclass, and :class:`GuardedSink`, the wrapper the pipeline puts around each sink so that a
sink's failure (a full disk, a closed Zenoh session) is counted and reported instead of
stopping estimation."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any, Protocol

# the pipeline's log: a sink's outage is reported where the pipeline reports everything else
log = logging.getLogger("sinewatch.core.pipeline")


class Sink(Protocol):
    """Where the pipeline's outputs go. ``log_time_ns`` is the input's receive time."""

    def on_input(self, key: str, payload: bytes, encoding: str, log_time_ns: int) -> None: ...
    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None: ...
    def on_error(self, key: str, payload: bytes, log_time_ns: int) -> None: ...
    # optional: ``on_estimates(estimates: list[tuple[str, bytes]], log_time_ns)``, each (key,
    # payload) as on_estimate takes it, in order, in one call (a frame's: GuardedSink.on_estimates)
    def on_status(self, key: str, payload: bytes, log_time_ns: int) -> None: ...
    def on_output(self, kind: str, key: str, payload: bytes, log_time_ns: int) -> None:
        """Any other output message; ``kind`` is its message name (e.g. ``HarmonicsReport``)."""

    def close(self) -> None: ...


class NullSink:
    """A sink that ignores everything; subclass and override what you need."""

    def on_input(self, key: str, payload: bytes, encoding: str, log_time_ns: int) -> None:
        pass

    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
        pass

    def on_error(self, key: str, payload: bytes, log_time_ns: int) -> None:
        pass

    def on_status(self, key: str, payload: bytes, log_time_ns: int) -> None:
        pass

    def on_output(self, kind: str, key: str, payload: bytes, log_time_ns: int) -> None:
        pass

    def close(self) -> None:
        pass


class GuardedSink:
    """A sink whose failures are caught, counted and reported, never raised into the
    pipeline: a full disk or a closed Zenoh session must not stop estimation. The sink's
    ``on_input``, ``on_estimate`` and ``on_output`` are looked up once, when it is wrapped.

    After a failure the sink is skipped (each output it misses is counted) for
    ``retry_s``; the next *input* after that reopens it (its ``recover()``, if it has
    one) and tries again. Recovery waits for an input so that a recorder restarts on a
    block boundary, where its state snapshot is exact.
    """

    def __init__(
        self,
        sink: Sink,
        name: str,
        on_failure: Callable[[str, str], None],
        *,
        retry_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.sink = sink
        self.name = name
        self._on_failure = on_failure
        self._retry_s = retry_s
        self._clock = clock
        self.ok = True
        self.failures = 0
        self.skipped = 0
        self.recoveries = 0
        self.last_error: str | None = None
        self._retry_at = 0.0
        # the sink's per-message methods, looked up once (None: NullSink's, which does nothing)
        self._on_input: Callable[[str, bytes, str, int], None] | None = _own_method(sink, "on_input")
        self._on_estimate: Callable[[str, bytes, int], None] | None = _own_method(sink, "on_estimate")
        self._on_output: Callable[[str, str, bytes, int], None] | None = _own_method(sink, "on_output")
        # a sink's own batch of estimates (a frame's), if it has one: else on_estimate each
        self._on_estimates: Callable[[list[tuple[str, bytes]], int], None] | None = getattr(sink, "on_estimates", None)

    def _call(self, method: str, *args: Any) -> None:
        if not self.ok and (method != "on_input" or self._clock() < self._retry_at or not self._recover()):
            self.skipped += 1
            return
        try:
            getattr(self.sink, method)(*args)
        except Exception as exc:  # noqa: BLE001 (a sink's fault is the sink's: isolate it, report it)
            self._fail(f"{method}", exc)

    def _recover(self) -> bool:
        recover = getattr(self.sink, "recover", None)
        try:
            if recover is not None:
                recover()
        except Exception as exc:  # noqa: BLE001 (still failing: stay failed, retry later)
            self._fail("recover", exc)
            return False
        self.ok = True
        self.recoveries += 1
        log.warning("sink %s: resumed after %d skipped output(s)", self.name, self.skipped)
        return True

    def _fail(self, where: str, exc: Exception) -> None:
        self.failures += 1
        self.last_error = f"{type(exc).__name__}: {exc}"
        first = self.ok
        self.ok = False
        self._retry_at = self._clock() + self._retry_s
        if first:  # one report per outage, not one per skipped output
            log.error(
                "sink %s failed in %s (%s); estimation goes on, retrying every %g s",
                self.name,
                where,
                self.last_error,
                self._retry_s,
            )
            self._on_failure(self.name, f"{self.name} failed in {where}: {self.last_error}")

    # The per-message methods: the same as _call(name, ...), without its getattr and
    # argument tuple (one call per block each, the pipeline's hot path); a method the sink
    # leaves as NullSink's (it does nothing) is not called at all while the sink is ok.
    def on_input(self, key: str, payload: bytes, encoding: str, log_time_ns: int) -> None:
        if not self.ok and (self._clock() < self._retry_at or not self._recover()):
            self.skipped += 1
            return
        if self._on_input is not None:
            try:
                self._on_input(key, payload, encoding, log_time_ns)
            except Exception as exc:  # noqa: BLE001 (a sink's fault is the sink's: isolate it, report it)
                self._fail("on_input", exc)

    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
        if not self.ok:
            self.skipped += 1
        elif self._on_estimate is not None:
            try:
                self._on_estimate(key, payload, log_time_ns)
            except Exception as exc:  # noqa: BLE001 (isolated, as in _call)
                self._fail("on_estimate", exc)

    def on_estimates(self, estimates: list[tuple[str, bytes]], log_time_ns: int) -> None:
        """Each (key, payload) of ``estimates`` as :meth:`on_estimate` takes it, in order, in
        one call (a frame's estimates): the sink's own ``on_estimates`` where it has one (the
        recorder, the Zenoh publisher: one loop without a call a layer an estimate), else its
        ``on_estimate`` for each. After a failure the rest of the batch is counted as skipped
        where the sink takes them one by one; a sink's own batch that fails is one failure (what
        it had not written is not counted)."""
        if not self.ok:
            self.skipped += len(estimates)
            return
        if self._on_estimates is not None:
            try:
                self._on_estimates(estimates, log_time_ns)
            except Exception as exc:  # noqa: BLE001 (isolated, as in _call)
                self._fail("on_estimates", exc)
            return
        on_estimate = self._on_estimate
        if on_estimate is None:
            return
        for i, (key, payload) in enumerate(estimates):
            try:
                on_estimate(key, payload, log_time_ns)
            except Exception as exc:  # noqa: BLE001 (isolated, as in _call)
                self._fail("on_estimate", exc)
                self.skipped += len(estimates) - i - 1
                return

    def on_error(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self._call("on_error", key, payload, log_time_ns)

    def on_status(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self._call("on_status", key, payload, log_time_ns)

    def on_output(self, kind: str, key: str, payload: bytes, log_time_ns: int) -> None:
        if not self.ok:
            self.skipped += 1
        elif self._on_output is not None:
            try:
                self._on_output(kind, key, payload, log_time_ns)
            except Exception as exc:  # noqa: BLE001 (isolated, as in _call)
                self._fail("on_output", exc)

    def open(self) -> None:
        if hasattr(self.sink, "open"):
            self._call("open")

    def flush(self) -> None:
        if self.ok and hasattr(self.sink, "flush"):
            self._call("flush")

    def close(self) -> None:
        try:
            self.sink.close()
        except Exception as exc:  # noqa: BLE001 (closing at shutdown: report, close the others)
            self.failures += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            log.error("sink %s failed to close: %s", self.name, self.last_error)

    def status(self) -> dict[str, Any]:
        names = ("name", "ok", "failures", "skipped", "recoveries", "last_error")
        return {name: getattr(self, name) for name in names}


def _own_method(sink: Sink, name: str) -> Any:
    """``sink.<name>`` (bound once), or None when it is NullSink's, which does nothing."""
    method = getattr(sink, name)
    return None if getattr(method, "__func__", None) is getattr(NullSink, name) else method
