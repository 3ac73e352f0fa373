"""An Estimate's bytes as the pipeline publishes them, built without the pydantic model (one
estimate per block is the pipeline's hot path): :func:`estimate_payload`, whose first branch
is the usual case (one ``%`` formatting of a template cached on the channel) and whose
second writes any case; both equal ``encode_estimate(estimate_model(...))`` byte for byte
(tests/test_codec_estimate_fast.py, tests/test_pipeline_hot_path.py)."""

from __future__ import annotations

import re
from collections.abc import Sequence
from math import isfinite
from typing import Any, Protocol

import numpy as np

from sinewatch.core.channel import Channel
from sinewatch.core.float_repr import MAX_CHARS, repr_floats, write_repr
from sinewatch.estimators.bank import ColumnTracks
from sinewatch.estimators.base import Track, TrackStd, kernel
from sinewatch.schemas.codec import (
    TIME_QUALITY_JSON,
    Block,
    encode_estimate_values,
    finite_or_none,
    json_string,
    time_quality_model,
)
from sinewatch.schemas.messages import Diagnostics, Estimate, Fencing, Uncertainty


class EstimateSettings(Protocol):
    """What an Estimate's bytes take from the pipeline besides the channel and the block."""

    estimate_version: int  # the Estimate format written (earlier ones reproduce earlier recordings)
    fencing_json: str  # the shard and term the daemon publishes under, as JSON ("null": none)


def estimate_payload(
    settings: EstimateSettings,
    ch: Channel,
    block: Block,
    track: Track,
    timestamp_ns: int,
    t_last_ns: int,
    gap_blocks: int,
    restart: bool,
    reset: bool,
    jump: bool = False,
    *,
    fast: bool = True,
) -> tuple[bytes, bool]:
    """The Estimate's bytes, and its ``converged``. From format 3 on, an estimate that is
    not valid (:func:`_present`, and every frequency and amplitude finite) is not converged
    either.

    The usual case (format 3 or later, every value a finite float64, no extras) is one ``%``
    formatting of a template cached on the channel (:func:`_estimate_template`) with every
    float written by one compiled call (:func:`sinewatch.core.float_repr.repr_floats`: each
    float's ``repr``, which is what :func:`encode_estimate_values` writes, at a fifth of
    CPython's cost). Any other case (or ``fast=False``, which tests
    use to compare the two ways: tests/test_pipeline_hot_path.py) goes through
    :func:`encode_estimate_values`, the same bytes as ``encode_estimate(estimate_model(...))``
    (tests/test_codec_estimate_fast.py)."""
    version = settings.estimate_version
    gap = gap_blocks > 0 or restart or jump
    if fast and version >= 3 and not track.extras:
        texts = _usual_texts(track)
        if texts is not None:  # the usual case: every value finite, so valid is presence alone
            valid = _present(ch, timestamp_ns, t_last_ns)
            converged = valid and bool(track.converged[-1])
            sec, nsec = divmod(int(timestamp_ns), 1_000_000_000)
            rms_text = texts.pop()  # the residual RMS's, last: the template takes it after the flags
            payload = _template(settings, ch, block, track) % (
                block.seq,
                int(timestamp_ns),
                sec,
                nsec,
                block.n_samples,
                *texts,
                _TRUE_FALSE[converged],
                _TRUE_FALSE[valid],
                rms_text,
                _TRUE_FALSE[gap],
                gap_blocks,
                _TRUE_FALSE[restart],
                _TRUE_FALSE[reset],
            )
            return payload.encode("ascii"), converged
    converged = bool(track.converged[-1])
    frequency_hz = _finite_list(track.frequency_hz[-1])
    amplitude = _finite_list(track.amplitude[-1])
    valid = True
    if version >= 3:
        valid = _present(ch, timestamp_ns, t_last_ns) and None not in frequency_hz and None not in amplitude
        converged = converged and valid
    std = track.std
    names = _json_names(ch)
    payload_bytes = encode_estimate_values(
        version,
        names[0],
        block.seq,
        int(timestamp_ns),
        block.n_samples,
        names[1],
        frequency_hz,
        amplitude,
        _finite_list(track.phase_rad[-1]),
        finite_or_none(track.offset[-1]),
        None if track.rocof_hz_per_s is None else _finite_list(track.rocof_hz_per_s[-1]),
        None
        if std is None
        else (
            _finite_list(std.frequency_hz[-1]),
            _finite_list(std.amplitude[-1]),
            _finite_list(std.phase_rad[-1]),
            finite_or_none(std.offset[-1]),
        ),
        converged,
        valid,
        finite_or_none(track.residual_rms),
        gap,
        gap_blocks,
        restart,
        reset,
        {k: _last_value(v) for k, v in track.extras.items()} if track.extras else {},
        settings.fencing_json,
        # the input's time quality (a frame's is each of its columns'), passed through as stated
        TIME_QUALITY_JSON[block.time_quality],
    )
    return payload_bytes, converged


def _present(ch: Channel, timestamp_ns: int, t_last_ns: int) -> bool:
    """The presence part of ``diagnostics.valid`` (format 3): the signal has been present (the
    presence detector, :mod:`sinewatch.estimators.presence`) from the estimator's memory before
    the estimate's time up to the block's last sample."""
    assert ch.presence is not None
    lag = max(0, round((t_last_ns - timestamp_ns) * ch.sample_rate_hz / 1e9))
    return ch.presence.run_samples >= ch.valid_memory_samples + lag


def _usual_texts(track: Track) -> list[str] | None:
    """The ``repr`` of every float of the estimate at the track's last row, in the order the
    template takes them, the residual RMS's last (``null`` when it is not finite); None when
    another value is not a finite float64 (then the general way writes it). A bank's channel
    reads its row of the whole frame's texts, written in one compiled call by the frame's first
    Estimate (:class:`~sinewatch.estimators.base.BankLastRow`); any other track one call of its own."""
    if track.bank_row is not None:
        bank, c = track.bank_row
        if bank.texts is None:
            values = bank.values
            bank.finite = np.isfinite(values[:, :-1]).all(axis=1).tolist()
            bank.texts = repr_floats(values.reshape(-1))
        width = bank.values.shape[1]
        rms, row_rms = track.residual_rms, bank.values.item(c, width - 1)
        # a bank that set the track's RMS after column_tracks (ipdft's own count of predictions)
        # leaves the row's stale: then the track's own way
        if rms == row_rms or (rms != rms and row_rms != row_rms):
            if not bank.finite[c]:  # type: ignore[index]  # (made with texts)
                return None
            texts = bank.texts[c * width : (c + 1) * width]
            if texts[-1] in _NOT_FINITE:
                texts[-1] = "null"
            return texts
    floats = _usual_floats(track)
    if floats is None:
        return None
    rms = track.residual_rms
    has_rms = rms is not None and isfinite(rms)
    if has_rms:
        floats.append(float(rms))
    texts = repr_floats(np.array(floats))  # every float's repr, in one compiled call
    if not has_rms:
        texts.append("null")
    return texts


_NOT_FINITE = ("nan", "inf", "-inf")


def _usual_floats(track: Track) -> list[float] | None:
    """Every float of the estimate at the track's last row, in the order the template takes
    them; None when one is not a finite float64 (then the general way writes it)."""
    std, rocof = track.std, track.rocof_hz_per_s
    floats = _one_component_floats(track.frequency_hz, track.amplitude, track.phase_rad, track.offset, rocof, std)
    if floats is None:  # several components, another dtype, or an array of another shape
        parts = [track.frequency_hz[-1], track.amplitude[-1], track.phase_rad[-1], track.offset[-1:]]
        if rocof is not None:
            parts.append(rocof[-1])
        if std is not None:
            parts += (std.frequency_hz[-1], std.amplitude[-1], std.phase_rad[-1], std.offset[-1:])
        values = np.concatenate(parts)
        if values.dtype != _F64:
            return None
        floats = values.tolist()
    # a NaN or an infinity makes the sum non-finite (so may an overflow: then the general way)
    return floats if isfinite(sum(floats)) else None


def _one_component_floats(
    f: np.ndarray, a: np.ndarray, p: np.ndarray, offset: np.ndarray, rocof: np.ndarray | None, std: TrackStd | None
) -> list[float] | None:
    """:func:`_usual_floats`'s values for one component (every estimator's usual case), each
    array's last element read as a Python float (``item``), without the slices and the
    concatenation of the general way (a quarter of an Estimate's bytes' time at 1,000 channels);
    None unless every array is a float64 ndarray of one column (rows, 1), the offsets (rows,)."""
    rows = [f, a, p] if rocof is None else [f, a, p, rocof]
    offsets = [offset]
    if std is not None:
        rows += (std.frequency_hz, std.amplitude, std.phase_rad)
        offsets.append(std.offset)
    for x in rows:
        if type(x) is not np.ndarray or x.dtype != _F64 or x.ndim != 2 or x.shape[1] != 1:
            return None
    for x in offsets:
        if type(x) is not np.ndarray or x.dtype != _F64 or x.ndim != 1:
            return None
    out = [f.item(-1), a.item(-1), p.item(-1), offset.item(-1)]
    if rocof is not None:
        out.append(rocof.item(-1))
    if std is not None:
        out += (std.frequency_hz.item(-1), std.amplitude.item(-1), std.phase_rad.item(-1), std.offset.item(-1))
    return out


def _template_key(settings: EstimateSettings, block: Block, track: Track) -> tuple[Any, ...]:
    """What an Estimate's template depends on besides the channel's names: format, components,
    rocof and std present, fencing, time quality."""
    return _layout_key(
        settings, block, track.frequency_hz.shape[-1], track.rocof_hz_per_s is not None, track.std is not None
    )


def _layout_key(settings: EstimateSettings, block: Block, k: int, rocof: bool, std: bool) -> tuple[Any, ...]:
    """:func:`_template_key` from the track's layout (``k`` components, rocof and std present)."""
    return (settings.estimate_version, k, rocof, std, settings.fencing_json, block.time_quality)


def _template(settings: EstimateSettings, ch: Channel, block: Block, track: Track) -> str:
    """The channel's cached template (:func:`_estimate_template`), made again when its layout
    (:func:`_template_key`) changes."""
    key = _template_key(settings, block, track)
    template = ch.template
    if template is None or template[0] != key:
        template = ch.template = (key, _estimate_template(_json_names(ch), *key))
    return template[1]


def _json_names(ch: Channel) -> tuple[str, str]:
    """The channel's and its estimator's names as JSON strings, made once per channel."""
    names = ch.json_names
    if names is None:
        names = ch.json_names = (json_string(ch.name), json_string(ch.estimator.name))
    return names


_TRUE_FALSE = ("false", "true")


def _estimate_template(
    names: tuple[str, str],
    version: int,
    k: int,
    rocof: bool,
    std: bool,
    fencing_json: str,
    time_quality: int,
) -> str:
    """The ``%`` template of an Estimate (format 3 or later, no extras) with ``k`` components:
    :func:`encode_estimate_values`'s layout, field for field, with ``%d`` for seq,
    timestamp_ns, sec, nsec, n_samples and gap_blocks, ``%s`` for each float's ``repr`` (in
    the order :func:`_usual_floats` gathers them) and for converged, valid,
    residual_rms, gap, restart and reset. Constant text is escaped (``%`` doubled)."""

    def const(text: str) -> str:
        return text.replace("%", "%%")

    floats = "[" + ",".join(["%s"] * k) + "]"
    out = (
        f'{{"format_version":{version},"channel":{const(names[0])},"seq":%d,"timestamp_ns":%d,'
        f'"timestamp":{{"sec":%d,"nsec":%d}},"n_samples":%d,"estimator":{const(names[1])},'
        f'"frequency_hz":{floats},"amplitude":{floats},"phase_rad":{floats},"offset":%s,'
        f'"rocof_hz_per_s":{floats if rocof else "null"},'
        + (
            f'"std":{{"frequency_hz":{floats},"amplitude":{floats},"phase_rad":{floats},"offset":%s}},'
            if std
            else '"std":null,'
        )
        + '"diagnostics":{"converged":%s,"valid":%s,"residual_rms":%s,"gap":%s,"gap_blocks":%d,'
        '"restart":%s,"reset":%s,"extras":{}}'
        + (f',"fencing":{const(fencing_json)}' if version >= 4 else "")
        + (f',"time_quality":{const(TIME_QUALITY_JSON[time_quality])}}}' if version >= 5 else "}")
    )
    return out


# ---- a bank's Estimates, every channel's bytes in one compiled call ---------------------------

# What a template's conversions take, in the order estimate_payload passes them: the five
# integers before the floats (seq, timestamp_ns, sec, nsec, n_samples), the floats, then
# converged, valid, the residual RMS, gap, gap_blocks, restart, reset. An op of the kernel says
# what goes between two constant pieces: an integer (_OP_INT + column of ``ints``), a float's
# repr (_OP_FLOAT + column of the values), a flag (_OP_FLAG + column of ``flags``), or the RMS
# (its repr, ``null`` when it is not finite).
_OP_INT, _OP_FLOAT, _OP_FLAG, _OP_RMS = 0, 1_000, 2_000, 3_000
_CONVERSION = re.compile(r"%[%ds]")


def _template_ops(n_floats: int) -> np.ndarray:
    """The ops of a template with ``n_floats`` floats before the RMS (see above)."""
    head = [_OP_INT + i for i in range(5)] + [_OP_FLOAT + f for f in range(n_floats)]
    tail = [_OP_FLAG + 0, _OP_FLAG + 1, _OP_RMS, _OP_FLAG + 2, _OP_INT + 5, _OP_FLAG + 3, _OP_FLAG + 4]
    return np.array(head + tail, dtype=np.int64)


def _template_pieces(template: str) -> tuple[bytes, list[int]]:
    """A ``%`` template's constant text (``%%`` read as ``%``) as ASCII and where each piece
    ends: the pieces between its conversions, one more than the conversions."""
    text, ends, at = [], [], 0
    for match in _CONVERSION.finditer(template):
        text.append(template[at : match.start()])
        at = match.end()
        if match.group() == "%%":
            text.append("%")
        else:
            ends.append(len("".join(text)))
    text.append(template[at:])
    joined = "".join(text)
    ends.append(len(joined))
    return joined.encode("ascii"), ends


@kernel(inline="always", refcount=False)
def _write_int(v: int, out: np.ndarray, at: int, digits: np.ndarray) -> int:
    """``str(v)`` of an integer as ASCII at ``out[at:]``; returns the index after it."""
    if v < 0:
        out[at] = 45  # -
        at += 1
        v = -v
    n = 0
    while True:  # the digits, last first
        digits[n] = 48 + v % 10
        v //= 10
        n += 1
        if v == 0:
            break
    for d in range(n - 1, -1, -1):
        out[at] = digits[d]
        at += 1
    return at


@kernel(inline="always", refcount=False)
def _write_text(text: np.ndarray, start: int, end: int, out: np.ndarray, at: int) -> int:
    for i in range(start, end):
        out[at] = text[i]
        at += 1
    return at


_FALSE = np.frombuffer(b"false", dtype=np.uint8)
_TRUE = np.frombuffer(b"true", dtype=np.uint8)
_NULL = np.frombuffer(b"null", dtype=np.uint8)


@kernel
def write_estimates_kernel(
    text: np.ndarray, ends: np.ndarray, ops: np.ndarray, ints: np.ndarray, bits: np.ndarray, flags: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Every channel's Estimate, back to back as ASCII, and where channel c's ends (``at[c + 1]``;
    ``at[0]`` = 0). ``text``: every channel's constant pieces back to back, channel c's piece p
    ending at ``ends[c, p]`` (the first starting where the previous channel's last ended); after
    piece p comes what ``ops[p]`` says (see ``_OP_INT`` above) from ``ints`` (C, 6) int64, ``bits``
    (C, F) the float64 values' IEEE 754 bits (the RMS last) or ``flags`` (C, 5: converged, valid,
    gap, restart, reset). What ``template % (...)`` gives, byte for byte."""
    nc, n_ops = ints.shape[0], ops.shape[0]
    out = np.empty(text.shape[0] + nc * n_ops * (MAX_CHARS + 1), dtype=np.uint8)
    at = np.zeros(nc + 1, dtype=np.int64)
    digits = np.empty(24, dtype=np.uint8)
    false, true, null = _FALSE, _TRUE, _NULL
    w = 0
    for c in range(nc):
        start = ends[c - 1, n_ops] if c else 0
        for p in range(n_ops + 1):
            w = _write_text(text, start, ends[c, p], out, w)
            start = ends[c, p]
            if p == n_ops:
                break
            op = ops[p]
            if op >= _OP_RMS:
                v = bits[c, bits.shape[1] - 1]
                finite = ((v >> np.uint64(52)) & np.uint64(0x7FF)) != np.uint64(0x7FF)
                w = write_repr(v, out, w, digits) if finite else _write_text(null, 0, 4, out, w)
            elif op >= _OP_FLAG:
                word = true if flags[c, op - _OP_FLAG] else false
                w = _write_text(word, 0, word.shape[0], out, w)
            elif op >= _OP_FLOAT:
                w = write_repr(bits[c, op - _OP_FLOAT], out, w, digits)
            else:
                w = _write_int(ints[c, op - _OP_INT], out, w, digits)
        at[c + 1] = w
    return out[:w], at


def warm_up_bank_payloads() -> None:
    """Load (or compile) :func:`write_estimates_kernel` for the arrays :func:`bank_payloads`
    hands it, so that a daemon's first frame does not wait for numba."""
    ops = _bank_ops(1)
    n_ops = ops.shape[0]
    write_estimates_kernel(
        np.frombuffer(b"{}" * (n_ops + 1), dtype=np.uint8),
        np.arange(2, 2 * n_ops + 3, 2, dtype=np.int64).reshape(1, n_ops + 1),
        ops,
        np.zeros((1, 6), dtype=np.int64),
        np.ones((1, 2)).view(np.uint64),
        np.zeros((1, 5), dtype=np.bool_),
    )


def bank_payloads(
    settings: EstimateSettings,
    chs: Sequence[Channel],
    blocks: Sequence[Block],
    tracks: Sequence[Track],
    t_last_ns: int,
    gaps: Sequence[tuple[int, bool, bool, bool]],
    run_samples: Sequence[int] | None = None,
    lag: int = 0,
    report_ns: int | None = None,
) -> list[tuple[bytes, bool, bool | None]] | None:
    """:func:`estimate_payload` of every channel of a bank at its frame's last sample (``gaps``:
    each channel's gap_blocks, restart, reset, time jump), the usual case of all of them written
    in one compiled call (:func:`write_estimates_kernel`) from the bank's last row
    (:class:`~sinewatch.estimators.base.BankLastRow`), each channel's template and its flags:
    the same bytes, channel by channel (tests/test_pipeline_hot_path.py). A channel with a value
    that is not finite goes through :func:`estimate_payload` (the general way). Each channel's
    (bytes, converged, valid), valid None where the general way wrote it (the bytes say it);
    None when the tracks are not one bank's usual case (then the caller writes each on its own).
    ``run_samples``: each channel's presence run after the block, when the caller has read it
    (``read_presence_bank``); else each detector's own. ``lag``, ``report_ns``: every channel's
    estimate at the block's sample ``lag`` before its last, whose time is ``report_ns``
    (validity rules version 6: at the detector's onset latency before it)."""
    timestamp_ns = t_last_ns if report_ns is None else report_ns
    if isinstance(tracks, ColumnTracks) and tracks.sealed and tracks.last_row is not None:
        # a bank's own Tracks, unread: the last row and converged flags without making them
        if settings.estimate_version < 3:
            return None
        values = tracks.last_row.values
        converged_last = tracks.converged_last()
        layout = _layout_key(settings, blocks[0], *tracks.layout)
    else:
        general = _bank_values(settings, tracks)
        if general is None:
            return None
        values = general
        converged_last = [bool(track.converged[-1]) for track in tracks]
        layout = _template_key(settings, blocks[0], tracks[0])  # a bank's tracks share their layout
    usual = np.isfinite(values[:, :-1]).all(axis=1).tolist()
    out: list[tuple[bytes, bool, bool | None] | None] = [None] * len(chs)
    templates, gap_blocks, flags, which = [], [], [], []
    for i, (ch, block, gap) in enumerate(zip(chs, blocks, gaps, strict=True)):
        if not usual[i]:
            out[i] = (*estimate_payload(settings, ch, block, tracks[i], timestamp_ns, t_last_ns, *gap), None)
            continue
        assert ch.presence is not None
        run = ch.presence.run_samples if run_samples is None else run_samples[i]
        valid = run >= ch.valid_memory_samples + lag  # _present
        converged = valid and converged_last[i]
        template = ch.template
        templates.append(
            template[1] if template is not None and template[0] == layout else _template(settings, ch, block, tracks[i])
        )
        gap_blocks.append(gap[0])
        flags.append((converged, valid, gap[0] > 0 or gap[1] or gap[3], gap[1], gap[2]))
        which.append(i)
    if not which:
        return out  # type: ignore[return-value]  # (every slot filled above)
    text, ends = _bank_pieces(tuple(templates), values.shape[1] - 1)
    sec, nsec = divmod(int(timestamp_ns), 1_000_000_000)
    block = blocks[which[0]]  # a frame's channels share seq, time and sample count
    ints = np.empty((len(which), 6), dtype=np.int64)
    ints[:, :5] = (block.seq, int(timestamp_ns), sec, nsec, block.n_samples)
    ints[:, 5] = gap_blocks
    data, at = write_estimates_kernel(
        text,
        ends,
        _bank_ops(values.shape[1] - 1),
        ints,
        (values[which] if len(which) < len(chs) else values).view(np.uint64),
        np.array(flags, dtype=np.bool_),
    )
    payloads, bounds = data.tobytes(), at.tolist()
    for j, i in enumerate(which):
        out[i] = (payloads[bounds[j] : bounds[j + 1]], flags[j][0], flags[j][1])
    return out  # type: ignore[return-value]  # (every slot filled above)


class BankWriting:
    """What :func:`usual_bank_payloads` keeps for one bank between frames: everything of its
    Estimates that stays the same from frame to frame while the layout does (the channels'
    templates cut into pieces, the ops, the memory each channel's valid flag compares its run
    with), made from what :func:`bank_payloads` leaves on the channels (:func:`bank_writing`)."""

    __slots__ = ("ends", "ints", "layout", "memory", "ops", "text")

    def __init__(self, layout: tuple[Any, ...], chs: Sequence[Channel], n_floats: int) -> None:
        self.layout = layout
        self.text, self.ends = _bank_pieces(tuple(ch.template[1] for ch in chs), n_floats)  # type: ignore[index]
        self.ops = _bank_ops(n_floats)
        self.memory = np.array([ch.fixed_valid_memory for ch in chs], dtype=np.int64)
        self.ints = np.zeros((len(chs), 6), dtype=np.int64)  # gap_blocks (column 5) stays 0


def bank_writing(
    settings: EstimateSettings, chs: Sequence[Channel], block: Block, tracks: Sequence[Track]
) -> BankWriting | None:
    """A bank's :class:`BankWriting`, once :func:`bank_payloads` has written every channel's
    Estimate the usual way (each channel's template made for this layout); None where it cannot
    be kept: another layout on some channel, or a channel whose memory may change (an
    estimator whose design follows the signal: ``Channel.fixed_valid_memory``)."""
    if settings.estimate_version < 3 or not (isinstance(tracks, ColumnTracks) and tracks.last_row is not None):
        return None
    layout = _layout_key(settings, block, *tracks.layout)
    for ch in chs:
        if ch.template is None or ch.template[0] != layout or ch.fixed_valid_memory is None:
            return None
    return BankWriting(layout, chs, tracks.last_row.values.shape[1] - 1)


def usual_bank_payloads(
    settings: EstimateSettings,
    writing: BankWriting,
    block: Block,
    tracks: Sequence[Track],
    t_last_ns: int,
    run_samples: Sequence[int],
    lag: int = 0,
) -> list[tuple[bytes, bool, bool | None]] | None:
    """:func:`bank_payloads` of a usual frame's bank (no gap, restart, reset or time jump on any
    channel) from what ``writing`` keeps: the same bytes, converged and valid, with no Python a
    channel before the compiled call. None, with nothing done, unless every channel's values are
    finite and the bank's Tracks are its own, unread, in ``writing``'s layout (then
    :func:`bank_payloads`). ``block``: any of the frame's columns (they share seq, time, sample
    count and time quality, all an Estimate reads of its block). ``t_last_ns``: the estimates'
    time, at the block's sample ``lag`` before its last (:func:`bank_payloads`)."""
    if not (isinstance(tracks, ColumnTracks) and tracks.sealed and tracks.last_row is not None):
        return None
    if settings.estimate_version < 3 or _layout_key(settings, block, *tracks.layout) != writing.layout:
        return None
    values = tracks.last_row.values
    if not np.isfinite(values[:, :-1]).all():
        return None
    valid = np.array(run_samples, dtype=np.int64) >= writing.memory + lag  # _present
    flags = np.zeros((values.shape[0], 5), dtype=np.bool_)  # converged, valid, gap, restart, reset
    flags[:, 1] = valid
    flags[:, 0] = valid & tracks.converged_last_array()
    sec, nsec = divmod(int(t_last_ns), 1_000_000_000)
    ints = writing.ints
    ints[:, :5] = (block.seq, int(t_last_ns), sec, nsec, block.n_samples)
    data, at = write_estimates_kernel(writing.text, writing.ends, writing.ops, ints, values.view(np.uint64), flags)
    payloads, bounds = data.tobytes(), at.tolist()
    converged_out, valid_out = flags[:, 0].tolist(), flags[:, 1].tolist()
    return [(payloads[bounds[c] : bounds[c + 1]], converged_out[c], valid_out[c]) for c in range(values.shape[0])]


def _bank_values(settings: EstimateSettings, tracks: Sequence[Track]) -> np.ndarray | None:
    """The bank's last row of every output for ``tracks`` (C-contiguous, a row a track), or None
    when they are not one bank's usual case: format 3 or later, every track a row of one
    :class:`BankLastRow`, no extras, no grid reports, the RMS still the track's (a bank that
    sets a track's RMS after column_tracks leaves the row's stale)."""
    first = tracks[0].bank_row
    if settings.estimate_version < 3 or first is None:
        return None
    bank = first[0]
    rows = []
    for track in tracks:
        row = track.bank_row
        if row is None or row[0] is not bank or track.extras or track.reports is not None:
            return None
        rows.append(row[1])
    values = bank.values if rows == list(range(bank.values.shape[0])) else np.ascontiguousarray(bank.values[rows])
    for rms, track in zip(values[:, -1].tolist(), tracks, strict=True):
        if not (rms == track.residual_rms or (rms != rms and track.residual_rms != track.residual_rms)):
            return None
    return values


_OPS: dict[int, np.ndarray] = {}
_PIECES: dict[tuple[str, ...], tuple[np.ndarray, np.ndarray]] = {}


def _bank_ops(n_floats: int) -> np.ndarray:
    ops = _OPS.get(n_floats)
    if ops is None:
        ops = _OPS[n_floats] = _template_ops(n_floats)
    return ops


def _bank_pieces(templates: tuple[str, ...], n_floats: int) -> tuple[np.ndarray, np.ndarray]:
    """The templates' constant pieces back to back (uint8) and where each piece ends (C, P + 1),
    as :func:`write_estimates_kernel` takes them; kept per tuple of templates (a bank's layout
    changes with its channels, the fencing or the format only)."""
    cached = _PIECES.get(templates)
    if cached is None:
        n_ops = _bank_ops(n_floats).shape[0]
        texts, ends, length = [], [], 0
        for template in templates:
            text, piece_ends = _template_pieces(template)
            if len(piece_ends) != n_ops + 1:
                raise ValueError(f"an Estimate template: expected {n_ops} conversions, got {len(piece_ends) - 1}")
            texts.append(text)
            ends.append([length + e for e in piece_ends])
            length += len(text)
        if len(_PIECES) > 4_096:
            _PIECES.clear()  # bounded: channels come and go
        cached = _PIECES[templates] = (np.frombuffer(b"".join(texts), dtype=np.uint8), np.array(ends, dtype=np.int64))
    return cached


_F64 = np.dtype(np.float64)


def _finite_list(row: np.ndarray) -> list[float | None]:
    """``[finite_or_none(v) for v in row]``, faster for the usual float64 row."""
    if type(row) is np.ndarray and row.dtype == _F64 and row.ndim == 1:
        return [v if isfinite(v) else None for v in row.tolist()]
    return [finite_or_none(v) for v in row]


def estimate_model(
    ch: Channel,
    block: Block,
    track: Track,
    timestamp_ns: int,
    converged: bool,
    valid: bool,
    gap_blocks: int,
    restart: bool,
    reset: bool,
    fencing: Fencing | None = None,
) -> Estimate:
    """The Estimate the pipeline's bytes encode, as the pydantic model: the schema's way of
    building it, what :func:`estimate_payload` equals byte for byte (tests)."""
    return Estimate(
        channel=ch.name,
        seq=block.seq,
        timestamp_ns=timestamp_ns,
        n_samples=block.n_samples,
        estimator=ch.estimator.name,
        frequency_hz=[finite_or_none(v) for v in track.frequency_hz[-1]],
        amplitude=[finite_or_none(v) for v in track.amplitude[-1]],
        phase_rad=[finite_or_none(v) for v in track.phase_rad[-1]],
        offset=finite_or_none(track.offset[-1]),
        rocof_hz_per_s=None if track.rocof_hz_per_s is None else [finite_or_none(v) for v in track.rocof_hz_per_s[-1]],
        std=None if track.std is None else _uncertainty(track.std),
        diagnostics=Diagnostics(
            converged=converged,
            valid=valid,
            residual_rms=finite_or_none(track.residual_rms),
            gap=gap_blocks > 0 or restart,
            gap_blocks=gap_blocks,
            restart=restart,
            reset=reset,
            extras={k: _last_value(v) for k, v in track.extras.items()},
        ),
        fencing=fencing,
        time_quality=time_quality_model(block.time_quality),
    )


def _uncertainty(std: TrackStd) -> Uncertainty:
    return Uncertainty(
        frequency_hz=[finite_or_none(v) for v in std.frequency_hz[-1]],
        amplitude=[finite_or_none(v) for v in std.amplitude[-1]],
        phase_rad=[finite_or_none(v) for v in std.phase_rad[-1]],
        offset=finite_or_none(std.offset[-1]),
    )


def _last_value(arr: np.ndarray) -> float | list[float | None] | None:
    last = arr[-1]
    if np.ndim(last) == 0:
        return finite_or_none(last)
    return [finite_or_none(v) for v in np.ravel(last)]
