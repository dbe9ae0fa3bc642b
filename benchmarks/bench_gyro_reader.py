"""Benchmark: GyroReader against the pty gyro twin running in its own process.

Measures, for a real-time 8 kHz stream (88 kB/s) over a pseudo-terminal:

- CPU of the reader thread (``time.thread_time`` inside it) and of this whole process, as %
  of one core; the twin runs in a subprocess so its CPU is not counted (it is reported);
- frames per second sustained, checksum errors, gaps;
- the clock model's rate error against the twin's true rate;
- on the very bytes the reader received (recorded with the reader's tap), the vectorised
  FrameParser against a naive per-byte Python parser: time per second of stream and the
  ratio.

Run: ``python benchmarks/bench_gyro_reader.py [--duration-s 10] [--read-period-s 0.02 ...]``.
Figures go to stdout, progress to stderr.
"""

from __future__ import annotations

import argparse
import json
import struct
import subprocess
import sys
import time
from collections.abc import Sequence

from timedexec.sensors import FrameParser, crc8, open_gyro

FRAME = 11


class NaiveParser:
    """The obvious per-byte state machine: sync, collect 11 bytes, CRC byte by byte,
    struct.unpack; on a bad CRC restart the search one byte after the failed sync."""

    def __init__(self) -> None:
        self.buf = bytearray()
        self.frames: list[tuple[int, int, int, int]] = []
        self.checksum_errors = 0
        self.table = [crc8(bytes([i])) for i in range(256)]  # init 0: the byte table

    def feed(self, data: bytes) -> None:
        buf = self.buf
        table = self.table
        for byte in data:
            if not buf:
                if byte == 0xA5:
                    buf.append(byte)
                continue
            if len(buf) == 1:
                if byte == 0x5A:
                    buf.append(byte)
                elif byte != 0xA5:
                    buf.clear()
                continue
            buf.append(byte)
            if len(buf) == FRAME:
                crc = 0
                for b in buf[2:10]:
                    crc = table[crc ^ b]
                if crc == buf[10]:
                    self.frames.append(struct.unpack_from("<Hhhh", buf, 2))
                    buf.clear()
                else:
                    self.checksum_errors += 1
                    rest = bytes(buf[1:])
                    buf.clear()
                    self.feed(rest)


def _start_twin(duration_s: float) -> tuple[subprocess.Popen[str], dict[str, float | str]]:
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "timedexec.twins",
            "gyro",
            "--duration-s",
            str(duration_s),
            "--profile",
            "sine",
            "--amplitude-dps",
            "100",
            "--frequency-hz",
            "2",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    ready = json.loads(proc.stdout.readline())
    return proc, ready


def run_reader(duration_s: float, read_period_s: float) -> dict[str, float]:
    """Stream from a twin subprocess for duration_s; return the figures."""
    proc, ready = _start_twin(duration_s + 3.0)
    chunks: list[bytes] = []
    try:
        with open_gyro(
            str(ready["slave_path"]),
            read_period_s=read_period_s,
            tap=lambda data, t: chunks.append(data),
        ) as gyro:
            cpu0 = time.process_time()
            wall0 = time.monotonic()
            n = 0
            while time.monotonic() - wall0 < duration_s:
                n += len(gyro.read(timeout_s=1.0))
                time.sleep(0.05)  # a consumer that picks up data 20 times a second
            cpu = time.process_time() - cpu0
            wall = time.monotonic() - wall0
            stats = gyro.stats
            fit = gyro.clock_fit()
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=10)
    summary = json.loads(out.splitlines()[-1]) if out.strip() else {}
    true_rate = float(ready["true_rate_hz"])
    stream = b"".join(chunks)
    return {
        "read_period_s": read_period_s,
        "wall_s": wall,
        "reader_cpu_pct": 100 * stats.reader_cpu_fraction,
        "process_cpu_pct": 100 * cpu / wall,
        "frames_per_s": stats.frames_ok / stats.reader_wall_s,
        "samples_consumed": n,
        "reads_per_s": stats.reads / stats.reader_wall_s,
        "checksum_errors": stats.checksum_errors,
        "gaps": stats.gaps,
        "rate_error_ppm_vs_truth": (fit.rate_hz / true_rate - 1) * 1e6,
        "twin_cpu_s": float(summary.get("cpu_s", float("nan"))),
        "stream": stream,  # type: ignore[dict-item]
        "chunk_sizes": [len(c) for c in chunks],  # type: ignore[dict-item]
    }


def compare_parsers(stream: bytes, chunk_sizes: list[int], stream_s: float) -> dict[str, float]:
    """Parse the recorded bytes with both parsers, chunked as the reader received them."""
    chunks = []
    pos = 0
    for size in chunk_sizes:
        chunks.append(stream[pos : pos + size])
        pos += size
    parser = FrameParser()
    t0 = time.process_time()
    n_fast = 0
    for chunk in chunks:
        n_fast += len(parser.feed(chunk))
    n_fast += len(parser.flush())
    fast_s = time.process_time() - t0

    naive = NaiveParser()
    t0 = time.process_time()
    for chunk in chunks:
        naive.feed(chunk)
    naive_s = time.process_time() - t0
    assert crc8(b"123456789") == 0xF4
    return {
        "frames_vectorised": n_fast,
        "frames_naive": len(naive.frames),
        "vectorised_pct_core": 100 * fast_s / stream_s,
        "naive_pct_core": 100 * naive_s / stream_s,
        "vectorised_us_per_chunk": 1e6 * fast_s / max(len(chunks), 1),
        "speedup": naive_s / fast_s if fast_s > 0 else float("inf"),
    }


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and print its figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration-s", type=float, default=10.0)
    parser.add_argument("--read-period-s", type=float, nargs="+", default=[0.02])
    args = parser.parse_args(argv)
    print(
        f"{'period':>8} {'reader%':>8} {'proc%':>7} {'frames/s':>9} {'reads/s':>8} "
        f"{'crc_err':>7} {'gaps':>5} {'ppm_err':>8} {'twin_cpu%':>9}"
    )
    last: dict[str, float] = {}
    for period in args.read_period_s:
        print(f"streaming {args.duration_s} s at read_period_s={period} ...", file=sys.stderr)
        r = run_reader(args.duration_s, period)
        print(
            f"{period:8.3f} {r['reader_cpu_pct']:8.2f} {r['process_cpu_pct']:7.2f} "
            f"{r['frames_per_s']:9.0f} {r['reads_per_s']:8.1f} {r['checksum_errors']:7d} "
            f"{r['gaps']:5d} {r['rate_error_ppm_vs_truth']:8.2f} "
            f"{100 * r['twin_cpu_s'] / (args.duration_s + 3):9.2f}"
        )
        last = r
    stream = last["stream"]  # type: ignore[assignment]
    stream_s = len(stream) / (8024 * FRAME)  # type: ignore[arg-type]
    print("parsing the same bytes again, vectorised vs per-byte ...", file=sys.stderr)
    cmp = compare_parsers(stream, last["chunk_sizes"], stream_s)  # type: ignore[arg-type]
    print(
        f"parser on {len(stream)} bytes ({stream_s:.1f} s of stream, "  # type: ignore[arg-type]
        f"{len(last['chunk_sizes'])} chunks):"  # type: ignore[arg-type]
    )
    print(
        f"  vectorised FrameParser: {cmp['vectorised_pct_core']:.3f} % of a core "
        f"({cmp['vectorised_us_per_chunk']:.0f} µs per chunk, hot), "
        f"{cmp['frames_vectorised']:.0f} frames"
    )
    print(
        f"  naive per-byte parser:  {cmp['naive_pct_core']:.2f} % of a core, "
        f"{cmp['frames_naive']:.0f} frames"
    )
    print(f"  speed-up: {cmp['speedup']:.0f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
