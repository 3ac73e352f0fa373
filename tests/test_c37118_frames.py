"""The C37.118.2-2011 frame codec (sinewatch.schemas.c37118) against the standard's tables:
field order, sizes and bit positions read back from the bytes at the offsets the tables give,
the CRC against its published check value and a bit-by-bit implementation, and every frame
cross-checked with an independent implementation (pyc37, the maintained fork of pypmu),
byte for byte where both encode the same content."""

from __future__ import annotations

import collections.abc  # pyc37 refers to collections.abc without importing it
import math
import struct
from dataclasses import replace

import pytest

from sinewatch.schemas.c37118 import (
    Command,
    ConfigFrame,
    DataError,
    DataFormat,
    FrameError,
    FrameSplitter,
    FrameType,
    PhasorScale,
    PmuConfig,
    PmuData,
    crc_ccitt,
    decode_command,
    decode_config,
    decode_data,
    decode_frame,
    encode_command,
    encode_config,
    encode_data,
    encode_header,
    fracsec_word,
    soc_fraction,
    stat_word,
    time_ns,
)

assert collections.abc
pyc37 = pytest.importorskip("pyc37.frame")
pymu_cfg = pytest.importorskip("pymu.pmuConfigFrame")
pymu_data = pytest.importorskip("pymu.pmuDataFrame")

SOC = 1_149_580_800  # 2006-06-06 08:00:00 UTC
ID = 7734


def F32(v: float) -> float:
    """v rounded to float32, as it travels in a float frame."""
    return struct.unpack(">f", struct.pack(">f", v))[0]


def crc_bitwise(data: bytes) -> int:
    """CRC-CCITT one bit at a time, straight from its definition (x^16 + x^12 + x^5 + 1, 0xFFFF)."""
    crc = 0xFFFF
    for byte in data:
        for i in range(7, -1, -1):
            bit = (byte >> i) & 1
            top = (crc >> 15) & 1
            crc = (crc << 1) & 0xFFFF
            if top ^ bit:
                crc ^= 0x1021
    return crc


def test_crc_ccitt_check_value_and_definition():
    assert crc_ccitt(b"123456789") == 0x29B1  # the CCITT-FALSE check value
    for data in (b"", b"\x00", b"\xaa\x41\x00\x12", bytes(range(256)) * 3):
        assert crc_ccitt(data) == crc_bitwise(data)


def test_command_frame_bytes_follow_table_14():
    fracsec = fracsec_word(16817, 0x0F)
    raw = encode_command(ID, Command.SEND_CFG2, SOC, fracsec)
    # SYNC AA, type 100 (command) version 0001 (a 2005 frame stays version 1); FRAMESIZE 18; IDCODE;
    # SOC; FRACSEC; CMD 5; CHK
    body = bytes.fromhex("AA41 0012 1E36 44853600 0F0041B1 0005")
    assert raw == body + crc_bitwise(body).to_bytes(2, "big")
    frame = decode_frame(raw)
    assert (frame.frame_type, frame.version, frame.id_code, frame.soc) == (FrameType.CMD, 1, ID, SOC)
    assert (frame.fraction, frame.time_quality) == (16817, 0x0F)
    assert decode_command(frame) == (5, b"")
    # pyc37 reads it the same way
    theirs = pyc37.CommandFrame.convert2frame(raw)
    assert (theirs.get_id_code(), theirs.get_command(), theirs.get_soc()) == (ID, "cfg2", SOC)
    # and writes the same bytes (version 1 is its only version)
    for cmd, name in [(1, "stop"), (2, "start"), (3, "header"), (4, "cfg1"), (5, "cfg2"), (6, "cfg3")]:
        mine = encode_command(ID, cmd, SOC, fracsec_word(16817, 0x0F))
        assert pyc37.CommandFrame(ID, name, soc=SOC, frasec=(16817, "+", False, False, 15)).convert2bytes() == mine


def test_fracsec_and_stat_bit_positions():
    # FRACSEC (Table 3): 31 reserved, 30 leap direction, 29 occurred, 28 pending, 27-24 quality, 23-0 fraction
    assert fracsec_word(0xFFFFFF, 0) == 0x00FFFFFF
    assert fracsec_word(0, 0xB) == 0x0B000000
    assert fracsec_word(0, 0, leap_pending=True) == 1 << 28
    assert fracsec_word(0, 0, leap_occurred=True) == 1 << 29
    assert fracsec_word(0, 0, leap_direction_negative=True) == 1 << 30
    with pytest.raises(ValueError, match="2\\^24"):
        fracsec_word(1 << 24)
    # STAT (Table 7)
    assert stat_word() == 0
    assert stat_word(DataError.PMU_ERROR) == 0b11 << 14
    assert stat_word(DataError.TEST_OR_ABSENT) == 0b10 << 14
    assert stat_word(in_sync=False) == 1 << 13
    assert stat_word(sorted_by_arrival=True) == 1 << 12
    assert stat_word(trigger=True) == 1 << 11
    assert stat_word(config_change=True) == 1 << 10
    assert stat_word(data_modified=True) == 1 << 9
    assert stat_word(pmu_time_quality=7) == 0b111 << 6
    assert stat_word(unlocked=3) == 0b11 << 4
    assert stat_word(trigger_reason=0xF) == 0xF


def test_time_base_rounding():
    assert soc_fraction(SOC * 10**9 + 20_000_000, 1_000_000) == (SOC, 20_000)
    assert soc_fraction(SOC * 10**9 + 999_999_999, 1_000_000) == (SOC + 1, 0)  # rounds into the next second
    assert soc_fraction(SOC * 10**9 + 1, 2**24 - 1) == (SOC, 0)
    for ns in (0, 20_000_000, 123_456_789, 999_999_000):
        soc, frac = soc_fraction(SOC * 10**9 + ns, 1_000_000)
        assert abs(time_ns(soc, frac, 1_000_000) - (SOC * 10**9 + ns)) <= 500


def _pmu(**kw) -> PmuConfig:
    base = dict(
        station="Station A",
        id_code=ID,
        format=DataFormat(polar=True),
        phasor_names=["VA", "VB", "VC"],
        phunit=[0, 0, 0],
        nominal_frequency_hz=50,
        cfgcnt=22,
    )
    base.update(kw)
    return PmuConfig(**base)


def test_cfg2_bytes_follow_table_8_and_match_pyc37():
    cfg = ConfigFrame(FrameType.CFG2, ID, 1_000_000, [_pmu()], 50, SOC, fracsec_word(16817, 0x0F))
    raw = encode_config(cfg)
    # Table 8, field by field, at the offsets the table gives
    assert raw[:2] == b"\xaa\x31"  # SYNC: CFG-2 (011), version 1
    assert int.from_bytes(raw[2:4], "big") == len(raw) == 14 + 4 + 2 + (16 + 2 + 2 * 4 + 3 * 16 + 3 * 4 + 4) + 2 + 2
    assert struct.unpack_from(">HII", raw, 4) == (ID, SOC, 0x0F0041B1)
    assert struct.unpack_from(">IH", raw, 14) == (1_000_000, 1)  # TIME_BASE, NUM_PMU
    assert raw[20:36] == b"Station A       "  # STN, 16 bytes space padded
    assert struct.unpack_from(">HHHHH", raw, 36) == (ID, 0x000F, 3, 0, 0)  # IDCODE FORMAT PHNMR ANNMR DGNMR
    assert raw[46:94] == b"VA" + b" " * 14 + b"VB" + b" " * 14 + b"VC" + b" " * 14  # CHNAM
    assert struct.unpack_from(">III", raw, 94) == (0, 0, 0)  # PHUNIT
    assert struct.unpack_from(">HHh", raw, 106) == (1, 22, 50)  # FNOM (bit 0: 50 Hz), CFGCNT, DATA_RATE
    assert int.from_bytes(raw[-2:], "big") == crc_bitwise(raw[:-2])
    theirs = pyc37.ConfigFrame2(
        ID, 1_000_000, 1, "Station A", ID, (True, True, True, True), 3, 0, 0,
        ["VA", "VB", "VC"], [(0, "v")] * 3, [], [], 50, 22, 50, soc=SOC, frasec=(16817, "+", False, False, 15),
    )  # fmt: skip
    assert theirs.convert2bytes() == raw
    back = decode_config(decode_frame(raw))
    assert back == replace(cfg, version=1)
    parsed = pyc37.CommonFrame.convert2frame(raw)
    assert parsed.get_station_name().strip() == "Station A" and parsed.get_data_rate() == 50


def test_cfg1_differs_only_in_the_frame_type():
    cfg2 = ConfigFrame(FrameType.CFG2, ID, 1_000_000, [_pmu()], 50, SOC, 0)
    cfg1 = ConfigFrame(FrameType.CFG1, ID, 1_000_000, [_pmu()], 50, SOC, 0)
    a, b = encode_config(cfg1), encode_config(cfg2)
    assert a[1] == 0x21 and b[1] == 0x31 and a[2:-2] == b[2:-2]
    assert decode_config(decode_frame(a)).frame_type is FrameType.CFG1


def test_cfg3_bytes_follow_table_10():
    pmu = _pmu(
        station="Süd-Ost 110 kV",
        phasor_names=["VA", "VB"],
        phunit=[],
        phscale=[PhasorScale(type_code=0b0100, scale=1.0), PhasorScale(flags=1 << 8, type_code=0b1101, user=9)],
        g_pmu_id=bytes(range(16)),
        latitude=47.5,
        longitude=8.25,
        elevation=400.0,
        service_class="M",
        window_us=120_000,
        group_delay_us=-60_000,
    )
    cfg = ConfigFrame(FrameType.CFG3, ID, 1_000_000, [pmu], -5, SOC, 0, cont_idx=0)
    raw = encode_config(cfg)
    assert raw[1] == 0x52  # CFG-3 (101), version 2
    assert struct.unpack_from(">HIH", raw, 14) == (0, 1_000_000, 1)  # CONT_IDX, TIME_BASE, NUM_PMU
    stn = "Süd-Ost 110 kV".encode()
    assert raw[22] == len(stn) and raw[23 : 23 + len(stn)] == stn  # STN: length, then UTF-8
    o = 23 + len(stn)
    assert struct.unpack_from(">H", raw, o) == (ID,)
    assert raw[o + 2 : o + 18] == bytes(range(16))  # G_PMU_ID
    assert struct.unpack_from(">HHHH", raw, o + 18) == (0x000F, 2, 0, 0)
    o += 26
    assert raw[o : o + 6] == b"\x02VA\x02VB"  # CHNAM, length-prefixed
    o += 6
    assert struct.unpack_from(">HBBffHBBff", raw, o) == (0, 0b0100, 0, 1.0, 0.0, 1 << 8, 0b1101, 9, 1.0, 0.0)
    o += 24
    assert struct.unpack_from(">fffcii", raw, o) == (47.5, 8.25, 400.0, b"M", 120_000, -60_000)
    o += 21
    assert struct.unpack_from(">HHh", raw, o) == (1, 22, -5)  # FNOM, CFGCNT, DATA_RATE (-5: one frame per 5 s)
    assert o + 6 + 2 == len(raw)
    assert decode_config(decode_frame(raw)) == replace(cfg, version=2)


def test_data_frame_float_polar_read_by_pymu():
    """pymu (an independent parser) reads our data frame; pyc37 cannot: its DataFrame re-checks a
    float FREQ against the integer format's +-32.767 deviation range, so 50 Hz is refused."""
    cfg = ConfigFrame(FrameType.CFG2, ID, 1_000_000, [_pmu()], 50, SOC, 0)
    stat = stat_word(DataError.PMU_ERROR_NO_INFO, in_sync=True, pmu_time_quality=7, data_modified=True)
    phasors = [(230.5, 0.25), (229.75, -1.5), (231.0, 2.75)]
    data = PmuData(stat, phasors, 50.0125, -0.375)
    raw = encode_data(cfg, SOC, fracsec_word(20_000, 0), [data])
    # Table 5: STAT, 3 x (magnitude, angle) floats, FREQ and DFREQ floats
    assert len(raw) == 14 + 2 + 3 * 8 + 8 + 2
    assert struct.unpack_from(">H6fff", raw, 14) == (stat, 230.5, 0.25, 229.75, -1.5, 231.0, 2.75, F32(50.0125), -0.375)
    back = decode_data(decode_frame(raw), cfg)
    assert back.pmus[0].phasors == phasors and back.pmus[0].freq_hz == F32(50.0125)
    assert back.pmus[0].data_error is DataError.PMU_ERROR_NO_INFO and back.pmus[0].in_sync
    their_cfg = pymu_cfg.ConfigFrame(encode_config(cfg).hex().upper())
    their_cfg.finishParsing()
    assert their_cfg.stations[0].stn.strip() == "Station A" and their_cfg.datarate == 50
    theirs = pymu_data.DataFrame(raw.hex().upper(), their_cfg).pmus[0]
    assert [(p.mag, p.rad) for p in theirs.phasors] == phasors
    assert theirs.freq == F32(50.0125) and theirs.dfreq * 100 == -0.375  # pymu divides a float DFREQ by 100 too
    assert (theirs.stat.dataError, theirs.stat.dataModified) == ("PMUERROR", "POSTPROCESSING")  # 01, bit 9


def test_data_frame_integer_formats_scale_as_table_5():
    pmu = _pmu(
        format=DataFormat(polar=False, phasor_float=False, analog_float=False, freq_float=False),
        phasor_names=["I1"],
        phunit=[(1 << 24) | 100],  # current, 0.001 A per bit
        analog_names=["P"],
        anunit=[(1 << 24) | 1000],  # 0.01 per bit
        digital_names=[f"B{i}" for i in range(16)],
        digunit=[0x0000FFFF],
        nominal_frequency_hz=60,
    )
    cfg = ConfigFrame(FrameType.CFG2, 3, 1_000_000, [pmu], 30)
    data = PmuData(0, [(1.5, -0.25)], 60.125, 0.5, [12.34], [0b1010])
    raw = encode_data(cfg, SOC, 0, [data])
    # STAT, real and imaginary (int16, / 0.001 A), FREQ deviation in mHz, DFREQ x 100, analog, digital
    assert struct.unpack_from(">HhhhhhH", raw, 14) == (0, 1500, -250, 125, 50, 1234, 0b1010)
    back = decode_data(decode_frame(raw), cfg).pmus[0]
    assert back.phasors == [(pytest.approx(1.5), pytest.approx(-0.25))]
    assert (back.freq_hz, back.dfreq_hz_per_s, back.digitals) == (60.125, 0.5, [0b1010])
    assert back.analogs == [pytest.approx(12.34)]
    cfg2 = decode_config(decode_frame(encode_config(cfg)))
    assert cfg2.pmus[0].nominal_frequency_hz == 60 and cfg2.pmus[0].digital_names[15] == "B15"


def test_header_frame_and_nan_phasors():
    raw = encode_header(ID, "sinewatch PMU", SOC, 0)
    assert raw[1] == 0x11 and decode_frame(raw).body == b"sinewatch PMU"
    cfg = ConfigFrame(FrameType.CFG2, ID, 1_000_000, [_pmu(format=DataFormat(polar=False))], 50)
    nan = math.nan
    raw = encode_data(cfg, SOC, 0, [PmuData(stat_word(DataError.TEST_OR_ABSENT), [(nan, nan)] * 3, nan, nan)])
    back = decode_data(decode_frame(raw), cfg).pmus[0]
    assert back.data_error is DataError.TEST_OR_ABSENT and all(math.isnan(a) for a, _ in back.phasors)


@pytest.mark.parametrize(
    ("mangle", "kind"),
    [
        (lambda b: b[:-1] + bytes([b[-1] ^ 1]), "crc"),  # CHK off by one bit
        (lambda b: b[:5] + bytes([b[5] ^ 0x10]) + b[6:], "crc"),  # a flipped bit in IDCODE
        (lambda b: b[:-3], "truncated"),  # fewer bytes than FRAMESIZE
        (lambda b: b"\x55" + b[1:], "sync"),
        (lambda b: b[:2] + b"\x00\x0a" + b[4:], "size"),  # FRAMESIZE below the minimum
    ],
)
def test_malformed_frames_are_rejected_with_a_reason(mangle, kind):
    good = encode_command(ID, Command.DATA_ON, SOC, 0)
    with pytest.raises(FrameError) as err:
        decode_frame(mangle(good))
    assert err.value.kind == kind


def test_command_without_cmd_word_is_truncated():
    raw = bytes.fromhex("AA41 0010 1E36 44853600 00000000")
    raw += crc_ccitt(raw).to_bytes(2, "big")
    with pytest.raises(FrameError) as err:
        decode_command(decode_frame(raw))
    assert err.value.kind == "truncated"


def test_splitter_reassembles_and_resynchronises():
    frames = [encode_command(ID, c, SOC, 0) for c in (1, 2, 5)]
    stream = b"".join(frames)
    s = FrameSplitter()
    got = []
    for i in range(0, len(stream), 7):  # arbitrary TCP segmentation
        got += s.feed(stream[i : i + 7])
    assert got == frames and s.pending == 0 and s.skipped == 0
    s = FrameSplitter()
    assert s.feed(b"\x00\x01garbage" + frames[0] + frames[1][:5]) == [frames[0]]
    assert s.skipped == 9 and s.pending == 5
    assert s.feed(frames[1][5:]) == [frames[1]]
