"""An Estimate's bytes as the pipeline publishes them, built without the pydantic model (one
estimate per block is the pipeline's hot path): :func:`estimate_payload`, whose first branch
is the usual case (one ``%`` formatting of a template cached on the channel) and whose
second writes any case; both equal ``encode_estimate(estimate_model(...))`` byte for byte
(tests/test_codec_estimate_fast.py, tests/test_pipeline_hot_path.py)."""

from __future__ import annotations

from math import isfinite
from typing import Protocol

import numpy as np

from sinewatch.core.channel import Channel
from sinewatch.core.float_repr import repr_floats
from sinewatch.estimators.base import Track, TrackStd
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


def _template(settings: EstimateSettings, ch: Channel, block: Block, track: Track) -> str:
    """The channel's cached template (:func:`_estimate_template`), made again when its layout
    (format, components, rocof and std present, fencing, time quality) changes."""
    rocof, std = track.rocof_hz_per_s is not None, track.std is not None
    key = (
        settings.estimate_version,
        track.frequency_hz.shape[-1],
        rocof,
        std,
        settings.fencing_json,
        block.time_quality,
    )
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
