"""COMTRADE in: files written here by the layout of IEEE Std C37.111-1999 / -2013 (clause 6:
the configuration file; clause 7: the data file, ASCII and binary; 2013 annex: the CFF
container) are read, fed to a real daemon and replayed, and estimated correctly.

The signal is known: three phases of 100 V peak at 50.2 Hz, 120 degrees apart, sampled at
2 kHz, stored as integers x with value = a * x + b (a = 100/30000 V per count: 16-bit
BINARY and ASCII), as 32-bit integers (BINARY32) or as floats (FLOAT32).
"""

from __future__ import annotations

import json
import struct
import subprocess
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
from conftest import cli_without, serve_comtrade, sinewatch
from mcap.reader import make_reader

from sinewatch.core.comtrade_file import ComtradeError, read_comtrade

FS = 2000.0
F = 50.2
AMPLITUDE = 100.0
PHASES = {"VA": 0.0, "VB": -2 * np.pi / 3, "VC": 2 * np.pi / 3}
N = 4000  # 2 s
START = datetime(2026, 11, 23, 10, 11, 12, 345678, tzinfo=UTC)
START_NS = 1795428672345678000  # START in ns since the epoch
B = 0.5  # an offset in the scaling: value = a * x + b
A16 = AMPLITUDE / 30000  # V per count, 16-bit
A32 = AMPLITUDE / 2e9  # V per count, 32-bit


def counts(a: float, n: int = N) -> dict[str, np.ndarray]:
    t = np.arange(n) / FS
    return {
        name: np.round((AMPLITUDE * np.sin(2 * np.pi * F * t + phi)) / a).astype(np.int64)
        for name, phi in PHASES.items()
    }


def write_comtrade(
    directory: Path,
    rev: str,
    ft: str,
    *,
    cff: bool = False,
    name: str = "rec",
    n_samples: int = N,
    station: str = "SUB STATION 1",
    encoding: str = "utf-8",
) -> Path:
    """A record of the three phases and one status channel, in revision ``rev`` (1999 or 2013)
    and data format ``ft`` (``n_samples`` long, the .cfg in ``encoding``); the .cfg path (or
    the .cff path)."""
    N = n_samples  # the module's record length, here this record's
    a = {"FLOAT32": 1.0, "BINARY32": A32}.get(ft, A16)
    x = counts(a, N) if ft != "FLOAT32" else dict.fromkeys(PHASES)
    t = np.arange(N) / FS
    values = {k: AMPLITUDE * np.sin(2 * np.pi * F * t + PHASES[k]) for k in PHASES}
    status = (np.arange(N) >= N // 2).astype(np.int64)  # a breaker opening half way
    lines = [f"{station},relay-7,{rev}", "4,3A,1D"]
    for i, k in enumerate(PHASES, 1):
        lo, hi = (-32767, 32767) if ft in ("ASCII", "BINARY") else (-(2**31) + 1, 2**31 - 1)
        if ft == "FLOAT32":
            lo, hi = -1, 1
        lines.append(f"{i},{k},{k[-1]},Line 1,kV,{a!r},{B!r},0,{lo},{hi},1,1,P")
    lines += ["1,52A,,Line 1,0", "50", "1", f"{FS:g},{N}"]
    stamp = START.strftime("%d/%m/%Y,%H:%M:%S.%f")
    lines += [stamp, stamp, ft, "1"]
    if rev == "2013":
        lines += ["0,0", "0,0"]
    cfg = "\r\n".join(lines) + "\r\n"
    ts = np.round(np.arange(N) * 1e6 / FS).astype(np.int64)  # microseconds (timemult 1)
    if ft == "ASCII":
        rows = [",".join([str(n + 1), str(ts[n]), *(str(x[k][n]) for k in PHASES), str(status[n])]) for n in range(N)]
        dat: bytes = ("\r\n".join(rows) + "\r\n").encode()
    else:
        fmt = {"BINARY": "<3h", "BINARY32": "<3i", "FLOAT32": "<3f"}[ft]
        out = bytearray()
        for n in range(N):
            out += struct.pack("<II", n + 1, ts[n])
            if ft == "FLOAT32":  # the values themselves (a = 1); the reader adds b
                out += struct.pack(fmt, *(values[k][n] for k in PHASES))
            else:
                out += struct.pack(fmt, *(int(x[k][n]) for k in PHASES))
            out += struct.pack("<H", status[n])
        dat = bytes(out)
    if cff:
        path = directory / f"{name}.cff"
        kind = "ASCII" if ft == "ASCII" else f"{ft}: {len(dat)}"
        path.write_bytes(
            f"--- file type: CFG ---\r\n{cfg}--- file type: INF ---\r\n--- file type: HDR ---\r\n"
            f"--- file type: DAT {kind} ---\r\n".encode()
            + dat
        )
        return path
    (directory / f"{name}.cfg").write_bytes(cfg.encode(encoding))
    (directory / f"{name}.dat").write_bytes(dat)
    return directory / f"{name}.cfg"


def expected_values(ft: str) -> dict[str, np.ndarray]:
    if ft == "FLOAT32":
        t = np.arange(N) / FS
        return {k: np.float32(AMPLITUDE * np.sin(2 * np.pi * F * t + PHASES[k])).astype(np.float64) + B for k in PHASES}
    a = A32 if ft == "BINARY32" else A16
    return {k: a * v.astype(np.float64) + B for k, v in counts(a).items()}


FORMATS = [
    ("1999", "ASCII", False),
    ("1999", "BINARY", False),
    ("2013", "ASCII", False),
    ("2013", "BINARY", False),
    ("2013", "BINARY32", False),
    ("2013", "FLOAT32", False),
    ("2013", "ASCII", True),
    ("2013", "BINARY", True),
]


@pytest.mark.parametrize(("rev", "ft", "cff"), FORMATS)
def test_each_revision_and_data_format_reads_to_the_written_values(tmp_path, rev, ft, cff):
    record = read_comtrade(write_comtrade(tmp_path, rev, ft, cff=cff))
    assert (record.rev_year, record.data_format, record.station) == (rev, ft, "SUB STATION 1")
    assert [c.channel for c in record.channels] == [f"comtrade/SUB-STATION-1/{k}" for k in PHASES]
    want = expected_values(ft)
    for c in record.channels:
        assert (c.sample_rate_hz, c.t0_ns, c.unit, len(c.samples)) == (FS, START_NS, "kV", N)
        np.testing.assert_allclose(c.samples, want[c.name], rtol=0, atol=1e-12)


def test_a_cfg_without_its_dat_and_a_non_comtrade_file_are_told(tmp_path):
    cfg = write_comtrade(tmp_path, "1999", "ASCII")
    cfg.with_suffix(".dat").unlink()
    with pytest.raises(ComtradeError, match=r"expected its data file .*rec\.dat, got no such file"):
        read_comtrade(cfg)
    (tmp_path / "x.cfg").write_text("not, a comtrade\nfile\n")
    with pytest.raises(ComtradeError, match="expected a COMTRADE record"):
        read_comtrade(tmp_path / "x.cfg")
    with pytest.raises(ComtradeError, match=r"expected a COMTRADE \.cfg or \.cff file, got a \.txt file"):
        read_comtrade(tmp_path / "x.txt")


IPDFT = ["--estimator", "ipdft", "--param", "nominal_frequency_hz=50", "--param", "window_cycles=10"]


def check_estimates(estimates: list[dict], channels: list[str]) -> None:
    """The last estimate of each phase against the truth: frequency, amplitude, offset, and
    the phase at the estimate's timestamp. The 16-bit quantisation (a = 3.3 mV) leaves errors
    near 1e-5 (measured: |df| <= 9e-6 Hz, |dA| <= 6e-5 V, |dphi| <= 6e-6 rad); the bounds
    are ten times that, and a time base off by one sample (0.16 rad) or a wrong scaling fails.
    The last valid one: a record's very last estimate is released at the feed's end with
    nothing after it to confirm its window (docs/validity.md), so it is not valid."""
    last = {e["channel"]: e for e in estimates if e["diagnostics"]["valid"]}
    assert sorted(last) == sorted(channels)
    for channel, e in last.items():
        phi0 = PHASES[channel.rsplit("/", 1)[1]]
        t = (e["timestamp_ns"] - START_NS) / 1e9
        assert e["diagnostics"]["converged"]
        assert abs(e["frequency_hz"][0] - F) < 1e-4, e
        assert abs(e["amplitude"][0] - AMPLITUDE) < 1e-3, e
        assert abs(e["offset"] - B) < 1e-3, e
        true_phase = 2 * np.pi * F * t + phi0
        assert abs(np.remainder(e["phase_rad"][0] - true_phase + np.pi, 2 * np.pi) - np.pi) < 1e-4, e


def test_replay_of_a_comtrade_file_estimates_it_and_records_a_replayable_run(tmp_path):
    cfg = write_comtrade(tmp_path, "2013", "FLOAT32")
    out = tmp_path / "run.mcap"
    r = subprocess.run(
        sinewatch("replay", str(cfg), *IPDFT, "--out", str(out), "--no-progress"),
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    assert "12 inputs replayed" in r.stdout  # 3 channels x 4 blocks of 1000 samples
    estimates = []
    with open(out, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            if channel.metadata["role"] == "estimate":
                estimates.append(json.loads(message.data))
    check_estimates(estimates, [f"comtrade/SUB-STATION-1/{k}" for k in PHASES])
    again = subprocess.run(
        sinewatch("replay", str(out), "--no-progress"), capture_output=True, text=True, timeout=120, check=False
    )
    assert again.returncode == 0 and "reproduced bit for bit" in again.stdout, again.stdout + again.stderr


def test_feed_comtrade_to_a_daemon(tmp_path):
    cfg = write_comtrade(tmp_path, "1999", "BINARY")
    feed_err, estimates = serve_comtrade(tmp_path, cfg)
    assert "published 12 blocks (12000 samples) on 3 channels" in feed_err
    assert "COMTRADE 1999 BINARY" in feed_err
    assert {e["seq"] for e in estimates} == {0, 1, 2, 3}
    check_estimates(estimates, [f"comtrade/SUB-STATION-1/{k}" for k in PHASES])
    first = min(estimates, key=lambda e: e["timestamp_ns"])
    assert first["timestamp_ns"] == START_NS + round(999 * 1e9 / FS)  # the block's last sample, at the file's time


def test_without_the_comtrade_package_the_error_names_the_extra(tmp_path):
    cfg = write_comtrade(tmp_path, "1999", "ASCII")
    r = cli_without("comtrade", ["replay", str(cfg)])
    assert r.returncode == 2
    assert r.stderr.splitlines() == [
        "sinewatch: error: COMTRADE: expected the comtrade package to be installed, got none "
        "(install the extra: pip install 'sinewatch[comtrade]')"
    ]


def two_rate_record(directory: Path, rates: str) -> Path:
    """A one-channel 1999 ASCII record whose sample-rate lines are ``rates``: 2000 Hz for
    samples 1-1000, then 1000 Hz for samples 1001-1500 (a fault recorder's usual slow-down).
    Sample 1001 comes 1/1000 s after sample 1000 (the step into a segment is at its rate, as
    python-comtrade reads it): at 999/2000 + 1/1000 = 0.5005 s."""
    n1, n2 = 1000, 500
    t = np.concatenate([np.arange(n1) / 2000.0, 0.5005 + np.arange(n2) / 1000.0])
    x = np.round(AMPLITUDE * np.sin(2 * np.pi * F * t) / A16).astype(int)
    head = ["S,R,1999", "1,1A,0D", f"1,IA,A,,A,{A16!r},0,0,-32767,32767,1,1,P", "50"]
    stamp = "01/02/2026,00:00:00.000000"
    cfg = "\r\n".join([*head, *rates.split("\n"), stamp, stamp, "ASCII", "1"])
    (directory / "two.cfg").write_text(cfg + "\r\n", newline="")
    rows = [f"{n + 1},{round(t[n] * 1e6)},{x[n]}" for n in range(n1 + n2)]
    (directory / "two.dat").write_text("\r\n".join(rows) + "\r\n", newline="")
    return directory / "two.cfg"


def test_each_sample_rate_segment_is_a_channel_at_its_rate_and_time(tmp_path):
    record = read_comtrade(two_rate_record(tmp_path, "2\n2000,1000\n1000,1500"))
    start = 1769904000 * 10**9  # 2026-02-01 00:00 UTC
    assert [(c.channel, c.sample_rate_hz, len(c.samples), c.t0_ns) for c in record.channels] == [
        ("comtrade/S/IA/seg1", 2000.0, 1000, start),
        ("comtrade/S/IA/seg2", 1000.0, 500, start + 500_500_000),  # sample 1001 at 0.5005 s
    ]
    t2 = 0.5005 + np.arange(500) / 1000.0
    np.testing.assert_allclose(record.channels[1].samples, AMPLITUDE * np.sin(2 * np.pi * F * t2), atol=A16)


def test_a_record_without_a_sample_rate_is_told(tmp_path):
    with pytest.raises(ComtradeError, match=r"expected a sample rate \(samp > 0\), got samp = 0"):
        read_comtrade(two_rate_record(tmp_path, "0\n0,1500"))  # nrates 0: timestamps only


def test_a_latin_1_cfg_is_read(tmp_path):
    """Older relays write the .cfg in Latin-1 (a station 'Umspannwerk Köln', o-umlaut byte
    0xF6, not UTF-8): it reads, its names decoded as Latin-1 (before: 'expected a COMTRADE
    record, got UnicodeDecodeError'). A UTF-8 .cfg still reads as UTF-8."""
    cfg = write_comtrade(tmp_path, "1999", "ASCII", station="Umspannwerk Köln", encoding="latin-1")
    assert b"K\xf6ln" in cfg.read_bytes()
    record = read_comtrade(cfg)
    assert record.station == "Umspannwerk Köln"
    assert [c.channel for c in record.channels] == [f"comtrade/Umspannwerk-K-ln/{k}" for k in PHASES]
    want = expected_values("ASCII")
    for c in record.channels:
        np.testing.assert_allclose(c.samples, want[c.name], rtol=0, atol=1e-12)
    utf8 = write_comtrade(tmp_path, "2013", "ASCII", station="Umspannwerk Köln", name="utf8")
    assert read_comtrade(utf8).station == "Umspannwerk Köln"


def test_a_record_shorter_than_the_estimator_window_is_told(tmp_path):
    """300 samples (0.15 s at 2 kHz) against a 10-cycle ipdft (a 0.2 s window): before, the
    replay exited 0 with every frequency NaN; now exit code 2 and a message naming the
    window and the length, and the Python API raises. A record that is long enough for its
    estimator still replays with exit code 0 (the test above)."""
    from sinewatch.estimators import get as get_estimator
    from sinewatch.runtime.replay import replay_comtrade
    from sinewatch.schemas.config import EstimatorRule

    need = get_estimator("ipdft")(FS, {"nominal_frequency_hz": 50, "window_cycles": 10}).memory_samples
    assert need > 300
    cfg = write_comtrade(tmp_path, "1999", "ASCII", n_samples=300)
    r = subprocess.run(
        sinewatch("replay", str(cfg), *IPDFT, "--no-progress"), capture_output=True, text=True, timeout=120, check=False
    )
    assert r.returncode == 2, r.stdout + r.stderr
    assert f"expected at least {need} samples (ipdft's window at 2000 Hz" in r.stderr and "got 300" in r.stderr
    rule = EstimatorRule(match="**", estimator="ipdft", params={"nominal_frequency_hz": 50, "window_cycles": 10})
    with pytest.raises(ComtradeError, match=r"VA: expected at least \d+ samples .*got 300.*no estimate can be valid"):
        replay_comtrade(cfg, rules=[rule])
