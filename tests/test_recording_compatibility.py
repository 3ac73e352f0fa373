"""Recordings outlive refactors: a run recorded by an earlier build still replays bit for bit.

``data/recorded-before-layering.mcap`` was recorded by sinewatch at the commit before the
source tree was reorganised into layers (every registered estimator at its example
parameters, 12 blocks each, through the real pipeline and MCAP recorder); its 12 ipdft
estimates were later rewritten, byte for byte this build's, when ipdft began reporting its
ROCOF's standard deviation in ``extras`` (the one field they gained; every other message is
the earlier build's, and its Estimate format has no ``std``), and again when ipdft's one-step
predictions took their sines by rotation between anchors and its band bins were summed by
segments shared between windows (frequency, amplitude, phase, offset, the residuals and the
ROCOF's standard deviation moved in their last 1-3 digits, ~1e-15 relative). The estimates of
kkl, kkl-biased and sogi-fll in it, and sogi-fll's in the two fixtures below, were rewritten byte
for byte this build's when those kernels' sin and tan became ``sinewatch.estimators.detmath``'s
instead of the C library's (their last bits: at most 2.2e-11 relative, in a ROCOF; every other
message and record the same). Its 12 adaptive-multisine estimates were rewritten, byte for byte
this build's, in November 2026 when the explicit design's observer gain L_x stopped going through
scipy's place_poles (OpenBLAS, whose kernels differ by CPU: the recording host's AVX-512 ones
gave other last bits than an AVX2 host's) and became Ackermann's formula in exactly rounded sums
(``sinewatch.estimators.detlinalg``), the same bits on every host; done with
``tests/rewrite_fixture_estimates.py``, which checks that every other record (header, schemas,
channels, metadata, every other message with its times and sequence) is unchanged. Then, the
same way, the estimates of kkl (12), kkl-biased (12), grip-mixing (12) and differential-rls (9),
when sinewatch began choosing OpenBLAS's Haswell kernels and numpy without its AVX-512 loops
on every x86-64 host with AVX2 and FMA (``sinewatch.host_arithmetic``): their designs go
through OpenBLAS, and the recording host's AVX-512 kernels had given their last bits. Any change
that alters an estimator's arithmetic, the estimate's JSON bytes or the replay reader
fails here.
"""

from __future__ import annotations

from pathlib import Path

from mcap.reader import make_reader

from sinewatch.runtime.replay import replay

FIXTURE = Path(__file__).parent / "data" / "recorded-before-layering.mcap"


def test_a_recording_made_before_the_layering_replays_bit_for_bit():
    result = replay([FIXTURE])
    assert result.inputs == 96 and result.recorded_estimates == 96
    assert result.ok, [m.describe() for m in result.mismatches[:5]]
    assert result.matched == 96


RAW_INPUTS = Path(__file__).parent / "data" / "recorded-sinewatch-block-v1.mcap"


def test_a_recording_with_raw_inputs_replays_bit_for_bit_rejected_inputs_included():
    """``data/recorded-sinewatch-block-v1.mcap`` was recorded by the build before inputs were
    recorded as protobuf InputBlock records: its inputs are the raw payloads (binary blocks on
    ``sinewatch-block-v1`` channels, float64 and float32; JSON blocks, some under an odd Zenoh
    encoding; 6 inputs the daemon rejected), nls and sogi-fll estimating."""
    result = replay([RAW_INPUTS])
    assert result.inputs == 42 and result.recorded_estimates == 36
    assert result.ok, [m.describe() for m in result.mismatches[:5]]
    assert result.matched == 36 and result.recorded_errors == result.produced_errors == 6


OLD_FRAMES = Path(__file__).parent / "data" / "recorded-sinewatch-frame-v1.mcap"


def test_a_recording_with_frames_in_their_own_layout_replays_bit_for_bit():
    """``data/recorded-sinewatch-frame-v1.mcap`` was recorded by the build before frames were
    recorded as protobuf InputFrame records: binary frames as received on
    ``sinewatch-frame-v1`` channels (3 channels float64, 2 channels float32 sniffed), JSON
    frames on ``json`` channels (two Zenoh encodings), 6 rejected frames (cut short, a
    non-zero pad byte, bad JSON) and single blocks beside them; nls and sogi-fll estimating."""
    with open(OLD_FRAMES, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    encodings = {(c.topic, c.message_encoding) for c in summary.channels.values() if c.metadata["role"] == "input"}
    assert ("sinewatch/in/f64/mu", "sinewatch-frame-v1") in encodings and ("sinewatch/in/js/mu", "json") in encodings
    result = replay([OLD_FRAMES])
    assert result.inputs == 30 and result.recorded_estimates == 48
    assert result.ok, [m.describe() for m in result.mismatches[:5]]
    assert result.matched == 48 and result.recorded_errors == result.produced_errors == 6
