"""RSI XML codec and answer latency (timedexec._rsi_xml, _rsi).

Prints, per frame:

1. parsing a full robot frame (RIst, RSol, AIPos, ASPos, Delay, IPOC) with
   :func:`parse_rob` against the obvious alternative, the same checks and extraction on
   :func:`defusedxml.ElementTree.fromstring`'s tree: the XML stage alone and the whole
   parse (ratios);
2. building the answer with :func:`build_sen` against building it with ElementTree (ratio);
3. the driver's turnaround on loopback: a scripted robot sends a frame and waits for the
   answer (median, 99th percentile, max), at 12 ms and at a 4 ms pace, and the driver's own
   receive-to-send latency.

Usage: python benchmarks/bench_rsi_xml.py [--n 20000] [--frames 500]
"""

from __future__ import annotations

import argparse
import socket
import time
import xml.etree.ElementTree as ET

import defusedxml.ElementTree as DET
import numpy as np

from timedexec import _rsi_xml
from timedexec._rsi_xml import AXIS_NAMES, build_rob, build_sen, parse_rob
from timedexec.drivers import KukaRSIDriver

FRAME = build_rob(
    123645634563,
    np.radians([10.0, -80.0, 85.0, 1.5, 30.0, -170.0]),
    aspos_rad=np.radians([10.0, -80.0, 85.0, 1.5, 30.0, -170.0]),
    rist=np.array([0.445, 0.0, 0.89, 0.1, 1.5, -0.2]),
    rsol=np.array([0.445, 0.0, 0.89, 0.1, 1.5, -0.2]),
    delay=0,
)


def defused_flat(raw: bytes, what: str) -> _rsi_xml._Flat:
    """The alternative XML stage: defusedxml's tree, reduced to what parse_rob reads."""
    root = DET.fromstring(raw, forbid_dtd=True, forbid_entities=True, forbid_external=True)
    flat = _rsi_xml._Flat()
    flat.root_tag = root.tag
    flat.root_attrib = dict(root.attrib)
    flat.root_text = [root.text or ""]
    for child in root:
        flat.children[child.tag] = dict(child.attrib)
        flat.text[child.tag] = [child.text or ""]
    return flat


def et_build(ipoc: int, corr: np.ndarray) -> bytes:
    sen = ET.Element("Sen", Type="ImFree")
    deg = np.degrees(corr)
    ET.SubElement(sen, "AK", {a: f"{v:.6f}" for a, v in zip(AXIS_NAMES, deg, strict=True)})
    ET.SubElement(sen, "IPOC").text = str(ipoc)
    return ET.tostring(sen)


def per_call_us(fn, n: int) -> float:  # type: ignore[no-untyped-def]
    fn()
    t = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t) / n * 1e6


def turnaround(period_s: float, frames: int) -> tuple[np.ndarray, np.ndarray]:
    with KukaRSIDriver(0, period_s=period_s) as drv:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        sock.settimeout(1.0)
        q = np.radians([10.0, -80.0, 85.0, 1.5, 30.0, -170.0])
        rtt = []
        ipoc = 123645634560
        next_t = time.monotonic()
        for _ in range(frames):
            next_t += period_s
            data = build_rob(ipoc, q, aspos_rad=q, delay=0)
            t = time.perf_counter()
            sock.sendto(data, ("127.0.0.1", drv.port))
            sock.recv(4096)
            rtt.append(time.perf_counter() - t)
            ipoc += round(period_s * 1000)
            time.sleep(max(0.0, next_t - time.monotonic()))
        sock.close()
        lat = []
        while drv.pending_states():
            s = drv.read_state(0.1)
            lat.append(s.answer_host_time_s - s.host_time_s)
    return np.array(rtt), np.array(lat)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=20000, help="codec repetitions")
    parser.add_argument("--frames", type=int, default=500, help="frames per turnaround run")
    args = parser.parse_args()

    xml_ours = per_call_us(lambda: _rsi_xml._parse_xml(FRAME, "Rob"), args.n)
    xml_theirs = per_call_us(lambda: defused_flat(FRAME, "Rob"), args.n)
    ours = per_call_us(lambda: parse_rob(FRAME), args.n)
    original = _rsi_xml._parse_xml
    _rsi_xml._parse_xml = defused_flat  # same checks and extraction, defusedxml's XML stage
    try:
        theirs = per_call_us(lambda: parse_rob(FRAME), args.n)
    finally:
        _rsi_xml._parse_xml = original
    print(f"frame: {len(FRAME)} bytes")
    print(f"XML stage  hardened expat (flat)   {xml_ours:7.1f} µs")
    print(
        f"XML stage  defusedxml tree         {xml_theirs:7.1f} µs   ratio "
        f"{xml_theirs / xml_ours:.2f}x"
    )
    print(f"parse_rob  hardened expat          {ours:7.1f} µs")
    print(f"parse_rob  on defusedxml           {theirs:7.1f} µs   ratio {theirs / ours:.2f}x")
    corr = np.radians([0.5, -1.0, 0.25, 0.0, 2.0, -0.1])
    ours_b = per_call_us(lambda: build_sen(123645634563, corr), args.n)
    theirs_b = per_call_us(lambda: et_build(123645634563, corr), args.n)
    print(f"build  build_sen            {ours_b:7.1f} µs")
    print(f"build  ElementTree          {theirs_b:7.1f} µs   ratio {theirs_b / ours_b:.2f}x")
    for period in (0.012, 0.004):
        rtt, lat = turnaround(period, args.frames)
        print(
            f"loopback turnaround at {period * 1e3:.0f} ms pace: median "
            f"{np.median(rtt) * 1e3:.3f} ms, p99 {np.percentile(rtt, 99) * 1e3:.3f} ms, max "
            f"{rtt.max() * 1e3:.3f} ms; driver rx->tx median {np.median(lat) * 1e3:.3f} ms, "
            f"p99 {np.percentile(lat, 99) * 1e3:.3f} ms ({len(rtt)} frames)"
        )


if __name__ == "__main__":
    main()
