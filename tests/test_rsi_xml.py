"""KUKA RSI XML frames: round trips, IPOC echo, hardening, fuzzing (timedexec._rsi_xml)."""

from __future__ import annotations

import contextlib
import math
import time

import defusedxml.ElementTree as DET
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from timedexec._rsi_xml import (
    MAX_FRAME_BYTES,
    RobFrame,
    build_rob,
    build_sen,
    parse_rob,
    parse_sen,
)
from timedexec.errors import ProtocolError

# A frame as a KR C4 sends it (format from the RSI documentation; values made up).
REAL_FRAME = (
    b'<Rob TYPE="KUKA"><RIst X="445.0000" Y="0.0000" Z="890.0000" A="0.0000" B="90.0000" '
    b'C="0.0000"/><RSol X="445.0000" Y="0.0000" Z="890.0000" A="0.0000" B="90.0000" '
    b'C="0.0000"/><AIPos A1="0.000000" A2="-90.000000" A3="90.000000" A4="0.000000" '
    b'A5="45.000000" A6="-180.000000"/><ASPos A1="0.000000" A2="-90.000000" A3="90.000000" '
    b'A4="0.000000" A5="45.000000" A6="-180.000000"/><Delay D="0"/>'
    b"<IPOC>123645634563</IPOC></Rob>"
)

BILLION_LAUGHS = (
    b'<?xml version="1.0"?><!DOCTYPE lolz [<!ENTITY lol "lol">'
    b'<!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">'
    b'<!ENTITY lol3 "&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;">'
    b'<!ENTITY lol4 "&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;">]>'
    b"<Rob><IPOC>&lol4;</IPOC></Rob>"
)
EXTERNAL_ENTITY = (
    b'<?xml version="1.0"?><!DOCTYPE Rob [<!ENTITY xxe SYSTEM "file:///etc/passwd">]>'
    b"<Rob><IPOC>&xxe;</IPOC></Rob>"
)
EXTERNAL_DTD = b'<?xml version="1.0"?><!DOCTYPE Rob SYSTEM "http://127.0.0.1:1/x.dtd"><Rob/>'
PARAMETER_ENTITY = (
    b'<?xml version="1.0"?><!DOCTYPE Rob [<!ENTITY % p SYSTEM "file:///etc/passwd"> %p;]>'
    b"<Rob><IPOC>1</IPOC></Rob>"
)
HOSTILE = [BILLION_LAUGHS, EXTERNAL_ENTITY, EXTERNAL_DTD, PARAMETER_ENTITY]


def _frame(**overrides: object) -> bytes:
    q = np.radians([10.0, -80.0, 85.0, 1.5, 30.0, -170.0])
    kwargs: dict[str, object] = {
        "aspos_rad": q + 1e-3,
        "rist": np.array([0.445, 0.0, 0.89, 0.1, 1.5, -0.2]),
        "delay": 3,
    }
    kwargs.update(overrides)
    return build_rob(123645634563, q, **kwargs)  # type: ignore[arg-type]


# ------------------------------------------------------------------ round trips


def test_real_frame_parses_to_si_units() -> None:
    """A frame in the documented KR C4 format parses; axes deg -> rad, RIst mm -> m."""
    f = parse_rob(REAL_FRAME)
    assert isinstance(f, RobFrame)
    assert f.ipoc == 123645634563  # beyond 2**32: no int32 truncation
    assert f.type == "KUKA"
    assert f.delay == 0
    assert f.aipos_rad is not None
    assert f.aspos_rad is not None
    assert f.rist is not None
    # Exact decimal degrees -> rad: only float rounding (1e-15) separates them.
    np.testing.assert_allclose(
        f.aipos_rad, np.radians([0, -90, 90, 0, 45, -180]), rtol=0, atol=1e-15
    )
    np.testing.assert_allclose(f.rist[:3], [0.445, 0.0, 0.89], rtol=0, atol=1e-15)
    np.testing.assert_allclose(f.rist[3:], np.radians([0, 90, 0]), rtol=0, atol=1e-15)
    assert f.rsol is not None


def test_rob_round_trip_within_wire_resolution() -> None:
    """build_rob -> parse_rob returns the values to the wire's resolution."""
    q = np.radians([10.123456789, -80.5, 85.25, 1.5, 30.0, -170.0])
    cart = np.array([0.4451234, -0.0123, 0.89, 0.1, 1.5, -0.2])
    f = parse_rob(build_rob(42, q, aspos_rad=q, rist=cart, rsol=cart, delay=7))
    assert f is not None
    assert f.aipos_rad is not None
    assert f.rist is not None
    # Axes are written with 6 decimals in degrees: rounding error <= 5e-7 deg = 8.8e-9 rad.
    np.testing.assert_allclose(f.aipos_rad, q, rtol=0, atol=9e-9)
    # Cartesian: 4 decimals in mm (5e-8 m) and in degrees (8.8e-7 rad).
    np.testing.assert_allclose(f.rist[:3], cart[:3], rtol=0, atol=5.1e-8)
    np.testing.assert_allclose(f.rist[3:], cart[3:], rtol=0, atol=8.8e-7)
    assert (f.ipoc, f.delay) == (42, 7)


def test_type_and_TYPE_alike_and_optional_elements() -> None:
    """`TYPE` and `Type` are read alike; elements not sent come back as None."""
    for attr in (b"TYPE", b"Type"):
        f = parse_rob(b"<Rob " + attr + b'="KUKA"><IPOC>5</IPOC></Rob>')
        assert f is not None
        assert f.type == "KUKA"
        assert f.aipos_rad is None
        assert f.aspos_rad is None
        assert f.rist is None
        assert f.delay is None


def test_unknown_elements_are_ignored() -> None:
    """Configurations that send extra signals (digital inputs, Tech values) still parse."""
    data = REAL_FRAME.replace(b"<Delay", b'<Digin D="5"/><Tech C11="1.0"><X a="1"/></Tech><Delay')
    f = parse_rob(data)
    assert f is not None
    assert f.ipoc == 123645634563


@pytest.mark.parametrize(
    "data", [b'<Rob TYPE="KUKA"></Rob>', b'<Rob TYPE="KUKA"/>', b'<Rob Type="KUKA">\n  </Rob>']
)
def test_initial_empty_frame_of_rsi_2_3_is_ignored(data: bytes) -> None:
    """RSI <= 2.3's first, empty <Rob> frame yields None (nothing to answer)."""
    assert parse_rob(data) is None
    assert parse_rob(build_rob(None)) is None


def test_sen_round_trip_and_defaults() -> None:
    """build_sen writes Type, the correction tag (AK by default) and the IPOC; parse_sen
    reads them back to the wire resolution."""
    corr = np.radians([0.5, -1.25, 0.0, 3.0, -0.000001, 10.0])
    data = build_sen(123645634563, corr)
    assert data.startswith(b'<Sen Type="ImFree"><AK A1="0.500000"')
    assert data.endswith(b"<IPOC>123645634563</IPOC></Sen>")
    sen = parse_sen(data, expected_type="ImFree")
    assert sen.ipoc == 123645634563
    assert sen.type == "ImFree"
    # 6 decimals in degrees: <= 5e-7 deg = 8.8e-9 rad.
    np.testing.assert_allclose(sen.correction_rad, corr, rtol=0, atol=9e-9)


def test_sen_custom_type_and_tag() -> None:
    """The SENTYPE and the correction element follow the RSI configuration."""
    data = build_sen(7, np.zeros(6), sen_type="KROSHU", correction_tag="AKorr")
    assert b'<Sen Type="KROSHU"><AKorr A1=' in data
    assert parse_sen(data, correction_tag="AKorr").ipoc == 7
    with pytest.raises(ProtocolError, match=r"no <AK> correction element"):
        parse_sen(data)
    with pytest.raises(ProtocolError, match=r"does not match the configured SENTYPE 'ImFree'"):
        parse_sen(data, correction_tag="AKorr", expected_type="ImFree")


@given(ipoc=st.integers(min_value=0, max_value=10**19 - 1))
def test_ipoc_echo_is_verbatim(ipoc: int) -> None:
    """Whatever IPOC the robot sends, the answer carries exactly the same digits."""
    rob = build_rob(ipoc, np.zeros(6))
    frame = parse_rob(rob)
    assert frame is not None
    answer = build_sen(frame.ipoc, np.zeros(6))
    assert f"<IPOC>{ipoc}</IPOC>".encode() in answer
    assert parse_sen(answer).ipoc == ipoc


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"ipoc": -1, "correction_rad": np.zeros(6)}, r"IPOC=-1 must be a non-negative"),
        ({"ipoc": 1, "correction_rad": np.zeros(5)}, r"5 values; expected 6"),
        ({"ipoc": 1, "correction_rad": [0, 0, math.nan, 0, 0, 0]}, r"non-finite"),
        ({"ipoc": 1, "correction_rad": np.zeros(6), "correction_tag": "A K"}, r"valid XML"),
        ({"ipoc": 1, "correction_rad": np.zeros(6), "sen_type": 'x"y'}, r"without < > &"),
    ],
)
def test_build_sen_rejects_bad_input(kwargs: dict[str, object], match: str) -> None:
    """An answer that would not be valid XML or RSI is refused with the reason."""
    with pytest.raises(ProtocolError, match=match):
        build_sen(**kwargs)  # type: ignore[arg-type]


# ------------------------------------------------------------------ hardening


@pytest.mark.parametrize("payload", HOSTILE, ids=["billion_laughs", "xxe", "dtd", "param"])
def test_entities_and_dtds_are_rejected_without_expansion(payload: bytes) -> None:
    """DTDs (and with them every entity declaration) are refused before anything is
    expanded or fetched, for both frame directions; defusedxml refuses the same payloads,
    which is the equivalence the module docstring claims."""
    t = time.perf_counter()
    with pytest.raises(ProtocolError, match=r"document type declaration \(DTD\)"):
        parse_rob(payload)
    with pytest.raises(ProtocolError, match=r"DTD"):
        parse_sen(payload.replace(b"Rob", b"Sen"))
    # Rejection is immediate: 50 ms is 1000x the typical 30 µs, room for a loaded machine.
    assert time.perf_counter() - t < 0.05
    with pytest.raises(Exception) as exc_info:  # noqa: PT011 - any defusedxml refusal
        DET.fromstring(payload, forbid_dtd=True)
    assert "Forbidden" in type(exc_info.value).__name__


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (
            b"x" * (MAX_FRAME_BYTES + 1),
            rf"{MAX_FRAME_BYTES + 1} bytes, above the limit of "
            rf"{MAX_FRAME_BYTES} bytes",
        ),
        (b"", r"empty"),
        (b"   \n", r"empty"),
        (b"<Rob><IPOC>1</IPOC>", r"not well-formed XML: no element found"),
        (b"<Rob><IPOC>&amp</IPOC></Rob>", r"not well-formed"),
        (b"<Rob><IPOC>&foo;</IPOC></Rob>", r"undefined entity"),
        (b"<Sen><IPOC>1</IPOC></Sen>", r"root element is <Sen>, expected <Rob>"),
        (b"<Rob><AIPos A1='1'/></Rob>", r"no <IPOC> element"),
        (b"<Rob><IPOC></IPOC></Rob>", r"IPOC='' is not a non-negative integer"),
        (b"<Rob><IPOC>-12</IPOC></Rob>", r"IPOC='-12' is not a non-negative integer"),
        (b"<Rob><IPOC>1_000</IPOC></Rob>", r"IPOC='1_000'"),
        ("<Rob><IPOC>١٢</IPOC></Rob>".encode(), r"ASCII digits"),
        (b"<Rob><IPOC>" + b"9" * 20 + b"</IPOC></Rob>", r"at most 19"),
        (b"<Rob><IPOC>1</IPOC><IPOC>2</IPOC></Rob>", r"more than one <IPOC>"),
        (b"<Rob><IPOC>1</IPOC><Delay D='x'/></Rob>", r"Delay.D='x'"),
        (b"<Rob><IPOC>1</IPOC><AIPos A1='1' A2='2'/></Rob>", r"<AIPos> lacks attribute A3"),
        (b"<Rob><IPOC>1</IPOC><RIst X='1'/></Rob>", r"<RIst> lacks attribute Y"),
    ],
)
def test_malformed_frames_name_the_problem(data: bytes, match: str) -> None:
    """Each kind of malformed frame raises ProtocolError saying what is wrong."""
    with pytest.raises(ProtocolError, match=match):
        parse_rob(data)


@pytest.mark.parametrize(
    "value", ["nan", "inf", "-Infinity", "1e999", "1_0", "0x10", "1.2.3", "", " ", "1e", "١"]
)
def test_axis_values_must_be_finite_plain_decimals(value: str) -> None:
    """Values Python's float() would accept (nan, inf, 1_0) or that overflow are refused,
    naming the element and attribute."""
    data = (
        f'<Rob><AIPos A1="0" A2="0" A3="{value}" A4="0" A5="0" A6="0"/><IPOC>1</IPOC></Rob>'
    ).encode()
    with pytest.raises(ProtocolError, match=r"AIPos.A3="):
        parse_rob(data)


def test_deep_nesting_and_non_bytes_are_rejected() -> None:
    """Nesting beyond 8 levels and non-bytes input are protocol errors, not crashes."""
    deep = b"<Rob><IPOC>1</IPOC>" + b"<a>" * 300 + b"</a>" * 300 + b"</Rob>"
    with pytest.raises(ProtocolError, match=r"deeper than 8 levels"):
        parse_rob(deep)
    with pytest.raises(ProtocolError, match=r"must be bytes, got str"):
        parse_rob("<Rob/>")  # type: ignore[arg-type]
    with pytest.raises(ProtocolError, match=r"must be bytes, got NoneType"):
        parse_sen(None)  # type: ignore[arg-type]


def test_huge_attribute_is_bounded_by_the_size_limit() -> None:
    """A huge attribute value is refused by size before parsing; a long but small-enough
    one by the number grammar, with the value shortened in the message."""
    huge = b'<Rob><IPOC>1</IPOC><AIPos A1="' + b"1" * 10**6 + b'"/></Rob>'
    with pytest.raises(ProtocolError, match=r"above the limit"):
        parse_rob(huge)
    long_value = "1" * 1000
    data = (
        f'<Rob><AIPos A1="{long_value}" A2="0" A3="0" A4="0" A5="0" A6="0"/><IPOC>1</IPOC></Rob>'
    ).encode()
    with pytest.raises(ProtocolError, match=r"AIPos.A1='1{37}\.\.\.' is not a decimal"):
        parse_rob(data)


# ------------------------------------------------------------------ fuzzing

_FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _parse_both(data: bytes) -> None:
    for parse in (parse_rob, parse_sen):
        with contextlib.suppress(ProtocolError):
            parse(data)


@_FUZZ
@given(data=st.binary(max_size=2 * MAX_FRAME_BYTES))
def test_fuzz_random_bytes_only_protocol_error(data: bytes) -> None:
    """Random bytes either parse or raise ProtocolError; nothing else escapes."""
    _parse_both(data)


@st.composite
def _mutated_frames(draw: st.DrawFn) -> bytes:
    base = bytearray(draw(st.sampled_from([REAL_FRAME, _frame(), build_sen(9, np.ones(6))])))
    for _ in range(draw(st.integers(1, 8))):
        op = draw(st.sampled_from(["flip", "insert", "delete", "splice"]))
        pos = draw(st.integers(0, len(base)))
        if op == "flip" and pos < len(base):
            base[pos] = draw(st.integers(0, 255))
        elif op == "insert":
            chunk = draw(
                st.sampled_from(
                    [
                        b"<",
                        b">",
                        b"&",
                        b"&lol;",
                        b'"',
                        b"<!DOCTYPE x>",
                        b"<![CDATA[x]]>",
                        b"<!-- c -->",
                        b"\x00",
                        b"\xff\xfe",
                        b"nan",
                        b"1e999",
                        b"<a>" * 20,
                        b"<IPOC>1</IPOC>",
                        b"<?pi x?>",
                    ]
                )
            )
            base[pos:pos] = chunk
        elif op == "delete":
            end = draw(st.integers(pos, min(len(base), pos + 20)))
            del base[pos:end]
        else:
            other = draw(st.sampled_from([REAL_FRAME, BILLION_LAUGHS, EXTERNAL_ENTITY]))
            cut = draw(st.integers(0, len(other)))
            base[pos:] = other[cut:]
    return bytes(base)


@_FUZZ
@given(data=_mutated_frames())
def test_fuzz_mutated_frames_only_protocol_error(data: bytes) -> None:
    """Byte flips, insertions (markup, entities, DTDs, NULs), deletions and splices of
    valid and hostile frames only ever raise ProtocolError."""
    _parse_both(data)
    # Whatever parses must carry sane values.
    try:
        f = parse_rob(data)
    except ProtocolError:
        return
    if f is not None:
        assert f.ipoc >= 0
        for arr in (f.aipos_rad, f.aspos_rad, f.rist, f.rsol):
            assert arr is None or (arr.shape == (6,) and np.all(np.isfinite(arr)))


@_FUZZ
@given(
    depth=st.integers(0, 2000),
    attr_len=st.integers(0, 5000),
    tag=st.sampled_from(["Rob", "Sen", "AIPos", "IPOC", "x"]),
)
def test_fuzz_structure_nesting_and_attribute_size(depth: int, attr_len: int, tag: str) -> None:
    """Arbitrary nesting depth and attribute sizes stay ProtocolError (size, depth) or
    parse; never RecursionError or MemoryError."""
    data = (
        f'<{tag} TYPE="{"K" * attr_len}">'
        + "<n>" * depth
        + "<IPOC>1</IPOC>"
        + "</n>" * depth
        + f"</{tag}>"
    ).encode()
    _parse_both(data)


# ------------------------------------------------------------------ speed


def test_parse_and_build_fit_the_4ms_cycle() -> None:
    """Parsing a full frame and building the answer take a small part of a 4 ms cycle.

    Typical: 30 µs parse, 10 µs build (benchmarks/bench_rsi_xml.py). The bound, 400 µs
    for both together (10 % of 4 ms), leaves a factor of 10 for loaded CI machines.
    """
    frame = _frame(rsol=np.zeros(6))
    corr = np.radians(np.arange(6.0))
    n = 500
    t = time.perf_counter()
    for _ in range(n):
        f = parse_rob(frame)
        assert f is not None
        build_sen(f.ipoc, corr)
    per_cycle = (time.perf_counter() - t) / n
    assert per_cycle < 400e-6, f"{per_cycle * 1e6:.0f} µs per frame"
