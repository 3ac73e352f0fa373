"""``sinewatch bench gateway``: IEC 61850-9-2LE sampled-value frames decoded and published
per core by ``sinewatch gateway sv``, against the rate one merging unit sends (4,000
frames/s at 50 Hz, 4,800 at 60 Hz: one ASDU per frame, 80 samples a cycle).

``--streams`` streams (svIDs) of ``--seconds`` seconds are rendered in memory with
open61850's own encoder (one second per stream, replayed with the counter wrapping and the
capture time advancing), then run three ways in this process, each timed by the CPU time
of the whole process (every thread: Zenoh's too):

* **decode**: open61850's ``decode_sv_frame`` alone, the baseline;
* **gateway**: the gateway's whole path without a transport (decode, filters, counter
  and quality checks, frames of ``--samples``);
* **gateway + Zenoh**: the same, each frame encoded and put on Zenoh (a peer session on
  loopback, a subscriber in a second session counting the frames, CongestionControl.BLOCK).

Reported per way: SV frames per CPU second (per core), its ratio to the decode baseline,
and how many 4,000- and 4,800-frame/s streams one core keeps up with.
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time
from typing import Any

from rich.table import Table

from sinewatch.apps.console import make_console, print_table

START = 1_700_000_000
RATES = (4000, 4800)


def _cpu() -> float:
    return time.process_time()  # every thread of the process, Zenoh's included


def render(streams: int, rate: int) -> list[list[bytes]]:
    """One second of 9-2LE frames per stream (a 50 Hz three-phase set, so a second repeats)."""
    from open61850 import sv
    from open61850 import sv_publisher as svp

    out = []
    for s in range(streams):
        waves = svp.three_phase(i_peak=400.0, v_peak=9000.0, freq_hz=50.0, i_lag_deg=30.0, layout="4I4U")
        stream = svp.SvStream(
            sv_id=f"MU{s:02d}", app_id=0x4000 + s, dst_mac=f"01:0c:cd:04:00:{s:02x}", src_mac="02:00:00:00:00:01",
            waves=waves, smp_synch=sv.SMP_SYNCH_GLOBAL,
        )  # fmt: skip
        template = svp.build_template(stream, 1, rate)
        out.append([svp.render_frame(template, stream, START, c, rate) for c in range(rate)])
    return out


def traffic(frames: list[list[bytes]], seconds: int, rate: int) -> list[tuple[bytes, int]]:
    """The streams interleaved as on a bus, with their capture times."""
    out: list[tuple[bytes, int]] = []
    for second in range(seconds):
        for c in range(rate):
            t = (START + second) * 1_000_000_000 + c * 1_000_000_000 // rate + 50_000
            out.extend((per_stream[c], t) for per_stream in frames)
    return out


def _timed(fn: Any) -> tuple[float, float]:
    wall, cpu = time.perf_counter(), _cpu()
    fn()
    return time.perf_counter() - wall, _cpu() - cpu


def run(args: argparse.Namespace) -> int:
    from open61850 import sv

    from sinewatch.apps.gateway import GatewayOptions, SvGateway

    console = make_console()
    rate = args.rate
    console.print(f"rendering {args.streams} stream(s) x {rate} frames with open61850 ...")
    bus = traffic(render(args.streams, rate), args.seconds, rate)
    n = len(bus)
    results: list[dict[str, Any]] = []

    def decode() -> None:
        for raw, _t in bus:
            sv.decode_sv_frame(raw)

    def gateway_only() -> None:
        gw = SvGateway(GatewayOptions(rate=rate, samples=args.samples), lambda name, f: None)
        for raw, t in bus:
            gw.feed(raw, t)
        gw.flush()
        if any(s.stats.lost or s.stats.repeated for s in gw.streams.values()):
            raise RuntimeError("the bench's own traffic was seen with gaps: a bug")

    for name, fn in (("decode (open61850)", decode), ("gateway", gateway_only)):
        wall, cpu = _timed(fn)
        results.append({"way": name, "frames": n, "wall_s": wall, "cpu_s": cpu})
    wall, cpu, received = _zenoh(bus, rate, args.samples, args.streams)
    results.append({"way": "gateway + Zenoh", "frames": n, "wall_s": wall, "cpu_s": cpu, "zenoh_frames": received})
    base = n / results[0]["cpu_s"]
    table = Table(title=f"SV frames decoded per core: {args.streams} stream(s) x {args.seconds} s at {rate}/s")
    for col in ("way", "frames/s per core", "vs decode", "streams/core @4000", "streams/core @4800", "wall s"):
        table.add_column(col, justify="left" if col == "way" else "right")
    for r in results:
        per_core = r["frames"] / max(r["cpu_s"], 1e-9)
        r.update(frames_per_cpu_s=per_core, vs_decode=per_core / base)
        r.update({f"streams_per_core_{k}": per_core / k for k in RATES})
        table.add_row(
            r["way"], f"{per_core:,.0f}", f"{per_core / base:.2f}", f"{per_core / 4000:.2f}",
            f"{per_core / 4800:.2f}", f"{r['wall_s']:.2f}",
        )  # fmt: skip
    print_table(console, table)
    console.print(f"load average at the end: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs (figures under load)")
    if args.json:
        args.json.write_text(json.dumps({"streams": args.streams, "rate": rate, "results": results}, indent=1))
    return 0


def _zenoh(bus: list[tuple[bytes, int]], rate: int, samples: int, streams: int) -> tuple[float, float, int]:
    """The gateway publishing on a loopback peer session, a second session subscribing."""
    import zenoh

    from sinewatch.apps.gateway import GatewayOptions, SvGateway
    from sinewatch.clients import BlockPublisher
    from sinewatch.clients.session import client_section, free_loopback_port, open_session

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    got = threading.Event()
    count = [0]
    expected = [0]
    with zenoh.open(conf) as listener, open_session(client_section([endpoint])) as session:

        def on_frame(_sample: Any) -> None:
            count[0] += 1
            if count[0] == expected[0]:
                got.set()

        sub = listener.declare_subscriber("sinewatch/in/*", on_frame)
        pub = BlockPublisher(session, dtype="float64")
        for s in range(streams):  # declare the publishers and see the subscriber before timing
            pub.wait_for_frame_subscriber(f"MU{s:02d}", 10.0)

        def publish() -> None:
            gw2 = SvGateway(
                GatewayOptions(rate=rate, samples=samples),
                lambda name, f: pub.publish_frame_raw(name, pub.encode_frame(f)),
            )
            for raw, t in bus:
                gw2.feed(raw, t)
            gw2.flush()
            expected[0] = pub.published
            if count[0] >= expected[0]:
                got.set()
            got.wait(60.0)

        wall, cpu = _timed(publish)
        expected_frames = expected[0]
        sub.undeclare()  # type: ignore[no-untyped-call]
        pub.close()
    if count[0] != expected_frames:
        raise RuntimeError(f"gateway + Zenoh: expected {expected_frames} frames at the subscriber, got {count[0]}")
    return wall, cpu, count[0]
