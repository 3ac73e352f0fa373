"""Is a channel's new block the continuation of what came before? One small check per block,
kept apart from the pipeline so that any data path (block by block, or frame by frame) calls
it per channel.

A block continues its channel when its sequence number is the next one and its first
sample's time is where the last block's samples end. Otherwise:

* a **gap**: sequence numbers missing (the blocks between were lost). The block is accepted
  and flagged; the pipeline's ``on_gap`` policy says whether the estimator coasts or resets.
* a **restart**: the number goes back while the time goes forward (a gateway rebooted and
  counts from 0 again, maybe after a long silence). Accepted, flagged.
* a **time jump**: the next number, but a first sample more than half a block (and more
  than one sample) away from where the stream was: the sender's clock stepped, or it
  dropped or repeated samples without a gap in its count. Accepted, flagged.
* a **duplicate** or a block **from the past** (the number goes back with its time): rejected.

Under the validity rules of version 2 (:data:`VALIDITY_RULES_VERSION`) a restart or a time
jump **starts the channel over**: whatever the estimator holds describes another stretch of
signal (45 s ago, or samples that are not where it thinks), so it is reset with the presence
detector, the estimate says ``reset: true`` and ``gap: true``, and nothing is valid until the
estimator's memory has refilled with the new stream. Version 1 (files recorded by earlier
builds) flagged a restart and let the estimator coast across it; replay keeps that rule for
those files so that they reproduce bit for bit.

Version 3 ends an absence only at 0.12 of the reference level (a hysteresis); with
``hold_estimates`` on (off by default then) it holds every estimate back until the presence
detector has read the channel's signal its onset latency past the estimate's window
(:attr:`sinewatch.estimators.presence.SignalPresence.onset_latency_samples`), so that no
estimate whose window holds the start of an interruption is published valid (the pipeline's
:func:`sinewatch.core.hold.hold`). Version 4 adds the detector's quarter-cycle onset test (the
signal against the sinusoid of its last reading), which cuts that latency to about a third of a
cycle. Version 5 calls a step of the level an edge (a sag's start and end: the presence run
starts over, presence (G)), wants two memories of signal behind a recursive estimator's estimate
(``Estimator.REFILL_MEMORIES``; one for a window) and judges a held estimate on the run at its
releasing block's end; ``hold_estimates`` is on by default from this version. Files of version 2
replay without the hold and the hysteresis, files of versions 3 and 4 with what their recorded
config says of the hold (version 3 without the quarter-cycle test), and without the edges and
the second memory. Version 6 (``report_in_block``, off by default) reports each block's estimate, with the hold on, at the sample
L = ``onset_latency_samples`` before the block's last instead of at its last (its
``timestamp_ns`` is that sample's): the detector runs first and has read L past it by the block's
end, so the hold confirms it and releases it with its own block instead of the next one (the
same guarantee, a block period less latency). A block of L samples or fewer, and an estimator
that reports on a time grid, report and hold as in version 5; files of version 5 replay as they
were made.
"""

from __future__ import annotations

from dataclasses import dataclass

from sinewatch.schemas.errors import InputError

#: Recorded in every file's metadata (``validity_rules_version``); files of earlier builds
#: have no key and replay under version 1. The rules a daemon runs unless its config asks for
#: :data:`REPORT_IN_BLOCK_RULES_VERSION`.
VALIDITY_RULES_VERSION = 5
#: The rules of a daemon whose config says ``report_in_block``: version 5's, each estimate
#: reported where its own block confirms it (the module's docstring).
REPORT_IN_BLOCK_RULES_VERSION = 6


def rules_version(report_in_block: bool) -> int:
    """The validity rules a new pipeline (and its recordings) run by, from its config."""
    return REPORT_IN_BLOCK_RULES_VERSION if report_in_block else VALIDITY_RULES_VERSION


@dataclass(frozen=True, slots=True)
class Continuity:
    """How a block follows its channel's previous one."""

    gap_blocks: int = 0  # sequence numbers missing before it
    restart: bool = False  # the sender restarted its count
    time_jump_ns: int = 0  # first sample minus where the stream was (0: contiguous, or unknown)

    @property
    def gap(self) -> bool:
        """The estimate's ``diagnostics.gap``: anything but a plain continuation."""
        return self.gap_blocks > 0 or self.restart or self.time_jump_ns != 0

    def starts_over(self, rules_version: int) -> bool:
        """Whether the channel starts over (estimator and presence reset) at this block."""
        return rules_version >= 2 and (self.restart or self.time_jump_ns != 0)


CONTINUES = Continuity()


def check_continuity(
    last_seq: int | None,
    next_t0_ns: int | None,
    seq: int,
    t0_ns: int,
    n_samples: int,
    sample_rate_hz: float,
    *,
    rules_version: int = VALIDITY_RULES_VERSION,
) -> Continuity:
    """The block ``(seq, t0_ns, n_samples)`` against its channel's last accepted one (``last_seq``
    and where its samples end, ``next_t0_ns``; None before the first). Raises InputError
    (``duplicate``, ``out_of_order``) for a block that cannot be accepted. A time jump is
    looked for (rules version 2) only where the count continues: across a gap of sequence
    numbers the time moves on by the lost blocks."""
    if last_seq is None:
        return CONTINUES
    if seq == last_seq + 1:
        if rules_version < 2 or next_t0_ns is None:
            return CONTINUES
        jump = t0_ns - next_t0_ns
        period_ns = 1e9 / sample_rate_hz
        if abs(jump) > max(0.5 * n_samples * period_ns, period_ns):
            return Continuity(time_jump_ns=jump)
        return CONTINUES
    if seq <= last_seq and next_t0_ns is not None and t0_ns >= next_t0_ns:
        return Continuity(restart=True)
    if seq == last_seq:
        raise InputError(f"seq: expected {last_seq + 1}, got {seq} again", kind="duplicate")
    if seq < last_seq:
        raise InputError(
            f"seq: expected {last_seq + 1}, got {seq} (older than the last accepted, and its t0_ns is not later either)",
            kind="out_of_order",
        )
    return Continuity(gap_blocks=seq - last_seq - 1)


__all__ = [
    "CONTINUES",
    "REPORT_IN_BLOCK_RULES_VERSION",
    "VALIDITY_RULES_VERSION",
    "Continuity",
    "check_continuity",
    "rules_version",
]
