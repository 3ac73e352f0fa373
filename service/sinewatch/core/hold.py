"""Estimates held back until the presence detector has read past their windows
(``hold_estimates``, on by default: docs/validity.md says what it costs): :func:`hold` takes a block's estimates
and gives what may leave now; :func:`not_valid` marks one that could not be confirmed; :func:`take_over` is what a change of
ownership does to what a channel holds (a deposed owner drops it: ``Pipeline.drop_held``)."""

from __future__ import annotations

import json

from sinewatch.core.channel import Channel


def hold(ch: Channel, t_last_ns: int, made: list[tuple[bytes, bool, int]], reset: bool) -> list[bytes]:
    """No estimate is published valid while its window may hold
    an event the presence detector has not read yet. Each estimate waits until the
    detector has seen ``onset_latency_samples`` past the last sample its window holds (its
    time's: the block's last, from validity rules version 6 with ``report_in_block`` that
    latency before it, so that it leaves with its own block; or a grid report's
    ``lookahead_samples`` after its time; counted in
    samples, not wall time: replay reproduces it), and is then published valid only if
    the signal was present at that sample throughout its window and since (the run of
    presence there reaches back to the window's start, which from validity rules version 5
    is ``Channel.valid_memory_samples`` before its end; and the run is read at the
    releasing block's last sample: an edge or a slower onset read by then counts too). An estimate not valid when made
    stays so; estimates held when the channel starts over (a reset) are published not
    valid: the detector that was to confirm them starts afresh. Order is kept: an
    estimate leaves after every estimate made before it."""
    assert ch.presence is not None
    out = _started_over(ch) if reset else []
    n_now = ch.samples
    latency = ch.presence.onset_latency_samples
    memory = ch.valid_memory_samples
    fs = ch.sample_rate_hz
    ahead = getattr(ch.estimator, "lookahead_samples", None)  # a grid report's window ends after its time
    held = ch.held
    for payload, converged, t_ns in made:
        valid = DIAGNOSTICS_VALID[0] in payload or DIAGNOSTICS_VALID[1] in payload
        lag = max(0, round((t_last_ns - t_ns) * fs / 1e9))
        # the window's last sample: the estimate's own (a block-end estimate's lag is 0 up to
        # validity rules version 5; from 6 the detector's latency, so that it leaves now)
        end = n_now - lag if ahead is None else min(n_now, n_now - lag + ahead)
        held.append((payload, end + latency, n_now - lag - memory if valid else -1, converged))
    return _released(ch, n_now, out)


def hold_at_end(
    ch: Channel,
    payload: bytes,
    valid: bool,
    converged: bool,
    reset: bool,
    latency: int | None = None,
    lag: int = 0,
) -> list[bytes]:
    """:func:`hold` of one estimate at its block's last sample whose ``valid`` is known (a bank's,
    written in one call: :func:`sinewatch.core.estimate_bytes.bank_payloads`), without reading
    it back from the bytes: the same estimates released, in the same order. ``latency``: the
    detector's ``onset_latency_samples`` now, when the caller has read it (a bank of detectors
    reads it for every channel at once: ``read_presence_bank``). ``lag``: the estimate is at
    the block's sample ``lag`` before its last (validity rules version 6 reports at the
    latency before it, so that this block's detector confirms it: released at once)."""
    assert ch.presence is not None
    out = _started_over(ch) if reset else []
    n_now = ch.samples
    ahead = getattr(ch.estimator, "lookahead_samples", None)
    end = n_now - lag if ahead is None else min(n_now - lag, n_now - lag + ahead)  # as hold's
    window_start = end - ch.valid_memory_samples if valid else -1
    if latency is None:
        latency = ch.presence.onset_latency_samples
    ch.held.append((payload, end + latency, window_start, converged))
    return _released(ch, n_now, out)


def _started_over(ch: Channel) -> list[bytes]:
    """What ``ch`` held when it starts over, all out now: not valid where it waited to be confirmed."""
    out = []
    held = ch.held
    while held:
        payload, _, window_start, _ = held.popleft()
        out.append(not_valid(payload) if window_start >= 0 else payload)
    return out


def _released(ch: Channel, n_now: int, out: list[bytes]) -> list[bytes]:
    """``out`` and, after it, every estimate ``ch`` holds whose release point the detector has
    reached (``n_now``: the channel's samples), each confirmed or made not valid by the run."""
    held = ch.held
    run = ch.last_run
    start = n_now if run is None else n_now - run.shape[0]  # the channel's sample count before this block
    converged_out = None
    while held and held[0][1] <= n_now:
        payload, at, window_start, converged = held.popleft()
        if window_start >= 0:
            # the run where the detector has read its latency past the window; from validity
            # rules version 5 at the block's last sample: an edge of the level (or an onset the
            # slower level test reads) found by then counts too
            i = max(at - start - 1, 0) if ch.validity_version < 5 or run is None else run.shape[0] - 1
            if run is None or run[i] < start + 1 + i - window_start:  # absent somewhere since the window began
                payload, converged = not_valid(payload), False
        out.append(payload)
        converged_out = converged
    if converged_out is not None:
        ch.converged = converged_out
    return out


DIAGNOSTICS_VALID = (
    b'"diagnostics":{"converged":true,"valid":true,',
    b'"diagnostics":{"converged":false,"valid":true,',
)
DIAGNOSTICS_NOT_VALID = b'"diagnostics":{"converged":false,"valid":false,'


def not_valid(payload: bytes) -> bytes:
    """An Estimate's bytes (format 3 or later) with ``valid`` and ``converged`` false: the
    diagnostics object's opening is unique in the message (names are JSON-escaped, so their
    quotes never read as these bytes)."""
    for flag in DIAGNOSTICS_VALID:
        if flag in payload:
            return payload.replace(flag, DIAGNOSTICS_NOT_VALID, 1)
    return payload


_FENCING = b',"fencing":'
_DECODER = json.JSONDecoder()


def take_over(ch: Channel, published_ns: int | None, fencing_json: str) -> int:
    """A change of ownership (a takeover, or a restart from a predecessor's state): the
    estimates ``ch`` holds were made under the term of the daemon whose state this is. One whose
    time is at or before ``published_ns`` (the last estimate of the channel the previous owner
    was seen to publish; None: none seen) is its, already out: dropped. The rest were never
    published: they keep their place and get ``fencing_json``, the term that now publishes
    them, so that no estimate leaves under a term this daemon does not hold. Returns how
    many were dropped."""
    kept = []
    for payload, at, window_start, converged in ch.held:
        if published_ns is not None and json.loads(payload)["timestamp_ns"] <= published_ns:
            continue
        kept.append((restamp(payload, fencing_json), at, window_start, converged))
    dropped = len(ch.held) - len(kept)
    ch.held.clear()
    ch.held.extend(kept)
    return dropped


def restamp(payload: bytes, fencing_json: str) -> bytes:
    """An Estimate's bytes with its ``fencing`` (format 4 or later) replaced by
    ``fencing_json``; earlier formats have none and are returned as they are. The member is the
    message's last ``,"fencing":`` (names and extras' strings are JSON-escaped, so their quotes
    never read as these bytes; extras sit inside diagnostics, before it)."""
    at = payload.rfind(_FENCING)
    if at < 0:
        return payload
    start = at + len(_FENCING)
    tail = payload[start:].decode("utf-8")
    _, n = _DECODER.raw_decode(tail)  # the old value's length, in characters
    return payload[:start] + fencing_json.encode("utf-8") + tail[n:].encode("utf-8")
