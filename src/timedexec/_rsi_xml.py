"""KUKA RSI (Ethernet RSI XML) frames: defensive parsing and fast building, both directions.

Robot -> PC, every controller cycle (content set by the RSI configuration's SEND list)::

    <Rob TYPE="KUKA"><RIst X=".." Y=".." Z=".." A=".." B=".." C=".."/>
    <AIPos A1=".." ... A6=".."/><ASPos A1=".." .../><Delay D="n"/><IPOC>123645634563</IPOC></Rob>

PC -> robot, the answer, which must echo the latest IPOC::

    <Sen Type="ImFree"><AK A1=".." ... A6=".."/><IPOC>123645634563</IPOC></Sen>

Axis values on the wire are in degrees, Cartesian positions in mm, Cartesian angles in
degrees; this module converts at the boundary so that everything it returns or accepts is SI
(rad, m). The PC side uses :func:`parse_rob` and :func:`build_sen`; the robot side (the
simulated controller :class:`timedexec.twins.RSITwin`) uses :func:`build_rob` and
:func:`parse_sen`.

Hardening
---------
The bytes come from the network, so parsing is defensive:

* a size limit (:data:`MAX_FRAME_BYTES`, 4 KiB; real frames are 300-600 bytes) is checked
  before any parsing;
* the XML goes through expat hardened exactly as :mod:`defusedxml` hardens it
  (``forbid_dtd``, ``forbid_entities``, ``forbid_external``, parameter-entity parsing off):
  a document type declaration is rejected the moment expat meets it, so no entity (internal
  "billion laughs" or external) can be declared, let alone expanded; undefined entity
  references are expat well-formedness errors. Nesting deeper than 8 levels is rejected.
  Why not :func:`defusedxml.ElementTree.fromstring` itself: it gives the same guarantees
  but builds a full tree through the pure-Python ``XMLParser``; collecting only the root
  and its direct children in expat's callbacks takes half the time (measured by
  ``benchmarks/bench_rsi_xml.py``: 2.0x for the XML stage and for the whole parse, about
  35 µs against 70 µs per frame), time the answer thread holds the GIL in every cycle. The
  test suite runs the hostile payloads through both and checks that both refuse them;
* numbers must match a plain ASCII decimal grammar and be finite (Python's ``float`` would
  also accept ``nan``, ``inf`` and ``1_0``; ``int`` would accept Unicode digits);
* every failure, whatever its cause, leaves as :class:`~timedexec.errors.ProtocolError`
  with a message naming what is wrong.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final
from xml.parsers import expat

import numpy as np
from numpy.typing import ArrayLike

from timedexec._types import FloatArray
from timedexec.errors import ProtocolError

__all__ = [
    "AXIS_NAMES",
    "CARTESIAN_NAMES",
    "MAX_FRAME_BYTES",
    "RobFrame",
    "SenFrame",
    "build_rob",
    "build_sen",
    "parse_rob",
    "parse_sen",
]


#: Largest frame accepted, bytes. Real RSI frames are 300-600 bytes; 4 KiB leaves room for
#: configurations that send extra signals while bounding the parser's work per cycle.
MAX_FRAME_BYTES: Final = 4096

#: Axis attribute names of AIPos / ASPos / AK, in joint order.
AXIS_NAMES: Final = ("A1", "A2", "A3", "A4", "A5", "A6")
#: Cartesian attribute names of RIst / RSol / RK: X, Y, Z in mm, A, B, C in degrees.
CARTESIAN_NAMES: Final = ("X", "Y", "Z", "A", "B", "C")

# Plain decimal numbers only: no nan/inf, no underscores, no Unicode digits.
_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]{1,3})?")
_NUMBERS6 = re.compile(rf"{_NUMBER.pattern}(?: {_NUMBER.pattern}){{5}}")
_MAX_INT_DIGITS: Final = 19  # IPOC fits an int64 / uint64 timestamp
_DEG: Final = math.pi / 180.0
_RAD: Final = 180.0 / math.pi
# Cartesian scale to SI: X, Y, Z mm -> m, A, B, C deg -> rad.
_CART_TO_SI: Final = np.array([1e-3, 1e-3, 1e-3, _DEG, _DEG, _DEG])
_MAX_DEPTH: Final = 8
_TAG_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]{0,31}")


@dataclass(frozen=True, kw_only=True, slots=True)
class RobFrame:
    """One robot -> PC frame, converted to SI.

    Attributes
    ----------
    ipoc : int
        The controller's interpolation-cycle time stamp; must be echoed in the answer.
    type : str
        The ``TYPE`` (or ``Type``) attribute of ``<Rob>`` (``"KUKA"``; empty if absent).
    aipos_rad : ndarray, shape (6,), or None
        Actual axis positions A1..A6, rad (``<AIPos>``, degrees on the wire).
    aspos_rad : ndarray, shape (6,), or None
        Set-point axis positions A1..A6, rad (``<ASPos>``).
    rist : ndarray, shape (6,), or None
        Actual Cartesian pose X, Y, Z (m) and A, B, C (rad) (``<RIst>``, mm and degrees).
    rsol : ndarray, shape (6,), or None
        Set-point Cartesian pose, same units (``<RSol>``).
    delay : int or None
        The controller's late-packet counter (``<Delay D="n"/>``).
    """

    ipoc: int
    type: str = "KUKA"
    aipos_rad: FloatArray | None = None
    aspos_rad: FloatArray | None = None
    rist: FloatArray | None = None
    rsol: FloatArray | None = None
    delay: int | None = None


@dataclass(frozen=True, kw_only=True, slots=True)
class SenFrame:
    """One PC -> robot answer as the robot reads it.

    Attributes
    ----------
    ipoc : int
        The echoed IPOC.
    type : str
        The ``Type`` attribute of ``<Sen>`` (must match the configuration's SENTYPE).
    correction_rad : ndarray, shape (6,)
        Axis correction A1..A6, rad (degrees on the wire).
    """

    ipoc: int
    type: str
    correction_rad: FloatArray


# --------------------------------------------------------------------------- parsing helpers


def _check_size(data: object, max_bytes: int) -> bytes:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(
            f"RSI frame must be bytes, got {type(data).__name__}; pass the datagram as received"
        )
    raw = bytes(data)
    if len(raw) > max_bytes:
        raise ProtocolError(
            f"RSI frame is {len(raw)} bytes, above the limit of {max_bytes} bytes; "
            "real frames are 300-600 bytes (raise max_bytes only if your RSI configuration "
            "really sends this much)"
        )
    if not raw.strip():
        raise ProtocolError("RSI frame is empty; expected an XML document")
    return raw


class _Flat:
    """Root and direct children of a small XML document, collected by a hardened expat run."""

    __slots__ = ("children", "depth", "duplicate", "root_attrib", "root_tag", "root_text", "text")

    def __init__(self) -> None:
        self.root_tag = ""
        self.root_attrib: dict[str, str] = {}
        self.root_text: list[str] = []
        self.children: dict[str, dict[str, str]] = {}
        self.text: dict[str, list[str]] = {}
        self.depth = 0
        self.duplicate = ""


def _forbidden(what: str) -> Callable[..., Any]:
    def handler(*_args: object) -> Any:
        raise ProtocolError(
            f"{what} in an RSI frame; RSI frames never contain a DTD, entity declarations "
            "or external references (rejected, nothing expanded)"
        )

    return handler


def _parse_xml(raw: bytes, what: str) -> _Flat:
    """Parse with expat, hardened like :mod:`defusedxml` (forbid_dtd, forbid_entities,
    forbid_external) and flat: only the root and its direct children are kept."""
    flat = _Flat()
    current = [""]
    parser = expat.ParserCreate()
    parser.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)
    parser.StartDoctypeDeclHandler = _forbidden("a document type declaration (DTD)")
    parser.EntityDeclHandler = _forbidden("an entity declaration")
    parser.UnparsedEntityDeclHandler = _forbidden("an unparsed entity declaration")
    parser.ExternalEntityRefHandler = _forbidden("an external entity reference")

    def start(name: str, attrs: dict[str, str]) -> None:
        flat.depth += 1
        if flat.depth == 1:
            flat.root_tag = name
            flat.root_attrib = attrs
        elif flat.depth == 2:
            if name in flat.children and not flat.duplicate:
                flat.duplicate = name
            flat.children[name] = attrs
            flat.text[name] = []
            current[0] = name
        elif flat.depth > _MAX_DEPTH:
            raise ProtocolError(
                f"{what} frame nests elements deeper than {_MAX_DEPTH} levels; RSI frames "
                "are two levels deep"
            )

    def end(_name: str) -> None:
        flat.depth -= 1

    def chars(data: str) -> None:
        if flat.depth == 2:
            flat.text[current[0]].append(data)
        elif flat.depth == 1:
            flat.root_text.append(data)

    parser.StartElementHandler = start
    parser.EndElementHandler = end
    parser.CharacterDataHandler = chars
    try:
        parser.Parse(raw, True)
    except expat.ExpatError as exc:
        raise ProtocolError(
            f"{what} frame is not well-formed XML: {expat.ErrorString(exc.code)} "
            f"at line {exc.lineno}, column {exc.offset}"
        ) from exc
    if flat.duplicate:
        raise ProtocolError(f"{what} frame has more than one <{flat.duplicate}> element")
    return flat


def _number(text: str | None, where: str) -> float:
    if text is None:
        raise ProtocolError(f"missing value: {where}")
    s = text.strip()
    if len(s) > 40 or _NUMBER.fullmatch(s) is None:
        shown = s if len(s) <= 40 else s[:37] + "..."
        raise ProtocolError(f"{where}={shown!r} is not a decimal number")
    value = float(s)
    if not math.isfinite(value):
        raise ProtocolError(f"{where}={s!r} is not finite")
    return value


def _integer(text: str | None, where: str) -> int:
    if text is None:
        raise ProtocolError(f"missing value: {where}")
    s = text.strip()
    if not s or len(s) > _MAX_INT_DIGITS or not (s.isascii() and s.isdigit()):
        shown = s if len(s) <= 40 else s[:37] + "..."
        raise ProtocolError(
            f"{where}={shown!r} is not a non-negative integer of at most "
            f"{_MAX_INT_DIGITS} ASCII digits"
        )
    return int(s)


def _vector(attrib: dict[str, str], names: tuple[str, ...], where: str) -> list[float]:
    try:
        texts = [attrib[name].strip() for name in names]
    except KeyError as exc:
        raise ProtocolError(
            f"<{where}> lacks attribute {exc.args[0]}; expected {', '.join(names)}"
        ) from None
    # Fast path: one regex over all six values, then float(); the slow path names the culprit.
    if _NUMBERS6.fullmatch(" ".join(texts)) is not None:
        values = [float(t) for t in texts]
        if all(map(math.isfinite, values)):
            return values
    return [_number(t, f"{where}.{name}") for t, name in zip(texts, names, strict=True)]


def _type_attr(attrib: dict[str, str]) -> str:
    value = attrib.get("TYPE")
    if value is None:
        value = attrib.get("Type", "")
    return value


# ------------------------------------------------------------------------------- PC side


def parse_rob(data: bytes, *, max_bytes: int = MAX_FRAME_BYTES) -> RobFrame | None:
    """Parse one robot -> PC ``<Rob>`` frame.

    Parameters
    ----------
    data : bytes
        The datagram as received.
    max_bytes : int, optional
        Size limit, bytes (default :data:`MAX_FRAME_BYTES`).

    Returns
    -------
    RobFrame or None
        The frame in SI units, or ``None`` for the empty ``<Rob>`` frame RSI <= 2.3 sends
        first (no children, no IPOC): it carries nothing and must not be answered.

    Raises
    ------
    ProtocolError
        For anything else that is not a valid ``<Rob>`` frame: too large, not XML, a DTD or
        entity, another root element, a missing or non-integer IPOC, a missing or
        non-numeric axis value, duplicated elements. No other exception type escapes.
    """
    try:
        return _parse_rob(data, max_bytes)
    except ProtocolError:
        raise
    except Exception as exc:  # defensive: any parser surprise is a protocol error
        raise ProtocolError(f"Rob frame could not be parsed ({type(exc).__name__}: {exc})") from exc


def _parse_rob(data: bytes, max_bytes: int) -> RobFrame | None:
    raw = _check_size(data, max_bytes)
    flat = _parse_xml(raw, "Rob")
    if flat.root_tag != "Rob":
        raise ProtocolError(f"root element is <{flat.root_tag[:40]}>, expected <Rob>")
    children = flat.children
    if not children and not "".join(flat.root_text).strip():
        return None  # RSI <= 2.3's initial empty frame
    if "IPOC" not in children:
        raise ProtocolError("Rob frame has no <IPOC> element; it cannot be answered")
    ipoc = _integer("".join(flat.text["IPOC"]), "IPOC")

    def axes(tag: str) -> FloatArray | None:
        attrib = children.get(tag)
        if attrib is None:
            return None
        return np.array(_vector(attrib, AXIS_NAMES, tag)) * _DEG

    def cart(tag: str) -> FloatArray | None:
        attrib = children.get(tag)
        if attrib is None:
            return None
        out: FloatArray = np.array(_vector(attrib, CARTESIAN_NAMES, tag)) * _CART_TO_SI
        return out

    delay_attrib = children.get("Delay")
    delay = None if delay_attrib is None else _integer(delay_attrib.get("D"), "Delay.D")
    return RobFrame(
        ipoc=ipoc,
        type=_type_attr(flat.root_attrib),
        aipos_rad=axes("AIPos"),
        aspos_rad=axes("ASPos"),
        rist=cart("RIst"),
        rsol=cart("RSol"),
        delay=delay,
    )


def _check_tag(tag: str, what: str) -> None:
    if _TAG_NAME.fullmatch(tag) is None:
        raise ProtocolError(f"{what}={tag!r} is not a valid XML name of at most 32 characters")


def _check_attr_value(value: str, what: str) -> None:
    if len(value) > 64 or any(c in value for c in "<>&\"'") or not value.isprintable():
        raise ProtocolError(
            f"{what}={value!r} must be printable, at most 64 characters, without < > & or quotes"
        )


def build_sen(
    ipoc: int,
    correction_rad: ArrayLike,
    *,
    sen_type: str = "ImFree",
    correction_tag: str = "AK",
) -> bytes:
    """Build the PC -> robot answer ``<Sen Type=..><AK A1=.. ../><IPOC>..</IPOC></Sen>``.

    Parameters
    ----------
    ipoc : int
        The IPOC of the frame being answered (echoed verbatim).
    correction_rad : array_like, shape (6,)
        Axis correction A1..A6, rad; written in degrees with 6 decimals (1.7e-8 rad).
    sen_type : str, optional
        ``Type`` attribute; must match the RSI configuration's SENTYPE.
    correction_tag : str, optional
        Correction element name from the RECEIVE configuration (``AK``, ``AKorr``, ...).

    Returns
    -------
    bytes
        The datagram, ASCII.
    """
    values = np.asarray(correction_rad, dtype=np.float64).reshape(-1)
    if values.shape != (6,):
        raise ProtocolError(f"correction has {values.size} values; expected 6 (A1..A6)")
    if not np.all(np.isfinite(values)):
        raise ProtocolError(f"correction {values.tolist()} contains non-finite values")
    if isinstance(ipoc, bool) or not isinstance(ipoc, (int, np.integer)) or ipoc < 0:
        raise ProtocolError(f"IPOC={ipoc!r} must be a non-negative integer")
    _check_tag(correction_tag, "correction_tag")
    _check_attr_value(sen_type, "sen_type")
    d = (values * _RAD).tolist()
    return (
        f'<Sen Type="{sen_type}"><{correction_tag} A1="{d[0]:.6f}" A2="{d[1]:.6f}" '
        f'A3="{d[2]:.6f}" A4="{d[3]:.6f}" A5="{d[4]:.6f}" A6="{d[5]:.6f}"/>'
        f"<IPOC>{int(ipoc)}</IPOC></Sen>"
    ).encode("ascii")


# ---------------------------------------------------------------------------- robot side


def build_rob(
    ipoc: int | None,
    aipos_rad: ArrayLike | None = None,
    *,
    aspos_rad: ArrayLike | None = None,
    rist: ArrayLike | None = None,
    rsol: ArrayLike | None = None,
    delay: int | None = 0,
    type_attr: str = "KUKA",
) -> bytes:
    """Build a robot -> PC ``<Rob>`` frame (used by the simulated controller).

    Parameters
    ----------
    ipoc : int or None
        Interpolation-cycle stamp; ``None`` builds RSI <= 2.3's initial empty frame
        (all other arguments ignored).
    aipos_rad, aspos_rad : array_like, shape (6,), optional
        Actual / set-point axis positions, rad (written in degrees, 6 decimals).
    rist, rsol : array_like, shape (6,), optional
        Actual / set-point Cartesian pose X, Y, Z (m) and A, B, C (rad); written in mm and
        degrees.
    delay : int or None, optional
        Late-packet counter for ``<Delay D=..>``; ``None`` omits the element.
    type_attr : str, optional
        ``TYPE`` attribute of ``<Rob>``.

    Returns
    -------
    bytes
        The datagram, ASCII.
    """
    _check_attr_value(type_attr, "type_attr")
    if ipoc is None:
        return f'<Rob TYPE="{type_attr}"></Rob>'.encode("ascii")
    parts = [f'<Rob TYPE="{type_attr}">']
    for tag, value in (("RIst", rist), ("RSol", rsol)):
        if value is not None:
            v = (np.asarray(value, dtype=np.float64).reshape(6) / _CART_TO_SI).tolist()
            parts.append(
                f'<{tag} X="{v[0]:.4f}" Y="{v[1]:.4f}" Z="{v[2]:.4f}" '
                f'A="{v[3]:.4f}" B="{v[4]:.4f}" C="{v[5]:.4f}"/>'
            )
    for tag, value in (("AIPos", aipos_rad), ("ASPos", aspos_rad)):
        if value is not None:
            d = (np.asarray(value, dtype=np.float64).reshape(6) * _RAD).tolist()
            parts.append(
                f'<{tag} A1="{d[0]:.6f}" A2="{d[1]:.6f}" A3="{d[2]:.6f}" '
                f'A4="{d[3]:.6f}" A5="{d[4]:.6f}" A6="{d[5]:.6f}"/>'
            )
    if delay is not None:
        parts.append(f'<Delay D="{int(delay)}"/>')
    parts.append(f"<IPOC>{int(ipoc)}</IPOC></Rob>")
    return "".join(parts).encode("ascii")


def parse_sen(
    data: bytes,
    *,
    correction_tag: str = "AK",
    expected_type: str | None = None,
    max_bytes: int = MAX_FRAME_BYTES,
) -> SenFrame:
    """Parse a PC -> robot ``<Sen>`` answer as the controller does.

    Parameters
    ----------
    data : bytes
        The datagram as received.
    correction_tag : str, optional
        Name of the correction element the RECEIVE configuration expects.
    expected_type : str, optional
        If given, the ``Type`` attribute must equal it (the configuration's SENTYPE).
    max_bytes : int, optional
        Size limit, bytes.

    Returns
    -------
    SenFrame

    Raises
    ------
    ProtocolError
        If the answer is not a valid ``<Sen>`` frame (same hardening as :func:`parse_rob`).
    """
    try:
        return _parse_sen(data, correction_tag, expected_type, max_bytes)
    except ProtocolError:
        raise
    except Exception as exc:  # defensive, as in parse_rob
        raise ProtocolError(f"Sen frame could not be parsed ({type(exc).__name__}: {exc})") from exc


def _parse_sen(
    data: bytes, correction_tag: str, expected_type: str | None, max_bytes: int
) -> SenFrame:
    raw = _check_size(data, max_bytes)
    flat = _parse_xml(raw, "Sen")
    if flat.root_tag != "Sen":
        raise ProtocolError(f"root element is <{flat.root_tag[:40]}>, expected <Sen>")
    sen_type = _type_attr(flat.root_attrib)
    if expected_type is not None and sen_type != expected_type:
        raise ProtocolError(
            f"Sen Type={sen_type[:40]!r} does not match the configured SENTYPE "
            f"{expected_type!r}; set sen_type to match the RSI configuration"
        )
    children = flat.children
    if "IPOC" not in children:
        raise ProtocolError("Sen frame has no <IPOC> element; the answer must echo the IPOC")
    ipoc = _integer("".join(flat.text["IPOC"]), "IPOC")
    corr_attrib = children.get(correction_tag)
    if corr_attrib is None:
        raise ProtocolError(
            f"Sen frame has no <{correction_tag}> correction element; found {sorted(children)[:8]}"
        )
    corr = np.array(_vector(corr_attrib, AXIS_NAMES, correction_tag)) * _DEG
    return SenFrame(ipoc=ipoc, type=sen_type, correction_rad=corr)
