"""GTP-U as it crosses N3 (TS 29.281), with the PDU Session Container of NR (TS 38.415).

A gNB hands every uplink IP packet of a UE to the UPF inside a G-PDU: an 8-byte GTP-U header
(version 1, protocol type GTP, message type 255, length, the tunnel's TEID), the 4 optional
octets (sequence number, N-PDU number, next extension header type) because an extension header
follows, and one extension header, the PDU Session Container (type 0x85), that says whether
the PDU goes up (UL PDU SESSION INFORMATION, PDU type 1) or down (DL, PDU type 0) and which QoS
flow (QFI, 6 bits) it belongs to. 16 bytes of GTP-U; with the outer IPv4 and UDP headers 44,
which is why a UE behind a 1500-byte N3 sees an MTU of 1456.

Echo Request / Echo Response (types 1 and 2, TEID 0, with a sequence number; the response
carries the Recovery IE, restart counter 0 as TS 29.281 §7.2.2 asks of GTP-U) are the path
check each end may send.

`encode_gpdu`/`echo_request`/`echo_response` build datagrams, `decode` reads any of them back
into a `GtpMessage`, raising `GtpError` (with what is wrong) for anything else. Pure bytes, no
sockets: `netem.gtpu.endpoint` is the endpoint that moves them.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from netem.errors import NetemError

#: The UDP port of GTP-U (TS 29.281 §4.4.2), on both ends of N3.
GTPU_PORT = 2152
GTP_VERSION = 1
ECHO_REQUEST, ECHO_RESPONSE, ERROR_INDICATION, END_MARKER, G_PDU = 1, 2, 26, 254, 255
EXT_NONE, EXT_PDU_SESSION_CONTAINER = 0x00, 0x85
PDU_TYPE_DL, PDU_TYPE_UL = 0, 1
IE_RECOVERY = 14
MAX_QFI = 63

_FLAG_PT, _FLAG_E, _FLAG_S, _FLAG_PN = 0x10, 0x04, 0x02, 0x01
_MANDATORY = struct.Struct("!BBHI")  # flags, message type, length, TEID
#: GTP-U bytes in front of each user packet on N3: mandatory 8, optional 4, container 4.
GPDU_HEADER_LEN = 16
#: Outer IPv4 (20) + UDP (8) + GTP-U (16): what N3 adds to each UE packet.
N3_OVERHEAD = 20 + 8 + GPDU_HEADER_LEN


class GtpError(NetemError, ValueError):
    """A datagram that is not a GTP-U message this endpoint understands; the text says why."""


@dataclass(frozen=True)
class GtpMessage:
    """One decoded GTP-U message: its type, TEID, sequence number (if present) and, for a
    G-PDU, the user packet and what its PDU Session Container said (`pdu_type`, `qfi`; None
    when it carried none)."""

    message_type: int
    teid: int
    sequence: int | None = None
    payload: bytes = b""
    pdu_type: int | None = None
    qfi: int | None = None

    @property
    def uplink(self) -> bool | None:
        return None if self.pdu_type is None else self.pdu_type == PDU_TYPE_UL


def _check_teid(teid: int) -> None:
    if not 0 <= teid <= 0xFFFFFFFF:
        raise GtpError(f"TEID must fit 32 bits, got {teid!r}")


def check_qfi(qfi: int) -> int:
    """`qfi` if it is a QoS flow identifier (0-63, TS 23.501 §5.7.1), else a GtpError."""
    if not isinstance(qfi, int) or not 0 <= qfi <= MAX_QFI:
        raise GtpError(f"QFI must be an integer 0-{MAX_QFI}, got {qfi!r}")
    return qfi


def encode_gpdu(teid: int, payload: bytes, qfi: int, uplink: bool, sequence: int = 0) -> bytes:
    """A G-PDU carrying `payload` in tunnel `teid`, with a PDU Session Container of `qfi`."""
    _check_teid(teid)
    check_qfi(qfi)
    if len(payload) > 0xFFFF - 8:
        raise GtpError(f"a {len(payload)}-byte packet does not fit one G-PDU")
    # UL: PDU type 1 in the high nibble, no delay/QMP flags; DL: PDU type 0, PPP and RQI off.
    container = bytes((1, (PDU_TYPE_UL if uplink else PDU_TYPE_DL) << 4, qfi, EXT_NONE))
    optional = struct.pack("!HBB", sequence & 0xFFFF, 0, EXT_PDU_SESSION_CONTAINER)
    flags = (GTP_VERSION << 5) | _FLAG_PT | _FLAG_E
    head = _MANDATORY.pack(flags, G_PDU, 8 + len(payload), teid)
    return head + optional + container + payload


def echo_request(sequence: int) -> bytes:
    """An Echo Request with sequence number `sequence` (TEID 0)."""
    flags = (GTP_VERSION << 5) | _FLAG_PT | _FLAG_S
    return _MANDATORY.pack(flags, ECHO_REQUEST, 4, 0) + struct.pack("!HBB", sequence & 0xFFFF, 0, 0)


def echo_response(sequence: int) -> bytes:
    """The Echo Response to the request with `sequence`: same sequence, Recovery IE 0."""
    flags = (GTP_VERSION << 5) | _FLAG_PT | _FLAG_S
    body = struct.pack("!HBB", sequence & 0xFFFF, 0, 0) + bytes((IE_RECOVERY, 0))
    return _MANDATORY.pack(flags, ECHO_RESPONSE, len(body), 0) + body


def decode(datagram: bytes) -> GtpMessage:
    """The GTP-U message in one UDP payload, or GtpError saying what is wrong with it."""
    if len(datagram) < _MANDATORY.size:
        raise GtpError(f"{len(datagram)} bytes is shorter than a GTP-U header (8)")
    flags, mtype, length, teid = _MANDATORY.unpack_from(datagram)
    version = flags >> 5
    if version != GTP_VERSION or not flags & _FLAG_PT:
        raise GtpError(f"not GTP-U: version {version}, protocol type {flags >> 4 & 1} (want 1, 1)")
    end = 8 + length
    if end > len(datagram):
        raise GtpError(
            f"length field says {length} bytes after the header, {len(datagram) - 8} there"
        )
    pos, sequence, pdu_type, qfi = 8, None, None, None
    if flags & (_FLAG_E | _FLAG_S | _FLAG_PN):
        if end < pos + 4:
            raise GtpError("flags announce the optional fields but the message is too short")
        seq, _npdu, next_type = struct.unpack_from("!HBB", datagram, pos)
        sequence = seq if flags & _FLAG_S else None
        pos += 4
        if flags & _FLAG_E:
            while next_type != EXT_NONE:
                if pos >= end:
                    raise GtpError(f"extension header 0x{next_type:02x} runs past the message")
                units = datagram[pos]
                if units == 0 or pos + 4 * units > end:
                    raise GtpError(f"extension header 0x{next_type:02x} has a bad length {units}")
                content = datagram[pos + 1 : pos + 4 * units - 1]
                if next_type == EXT_PDU_SESSION_CONTAINER:
                    pdu_type, qfi = content[0] >> 4, content[1] & 0x3F
                next_type = datagram[pos + 4 * units - 1]
                pos += 4 * units
    if mtype not in (G_PDU, ECHO_REQUEST, ECHO_RESPONSE, ERROR_INDICATION, END_MARKER):
        raise GtpError(f"unknown GTP-U message type {mtype}")
    payload = bytes(datagram[pos:end]) if mtype == G_PDU else b""
    return GtpMessage(mtype, teid, sequence, payload, pdu_type, qfi)


__all__ = [
    "ECHO_REQUEST",
    "ECHO_RESPONSE",
    "GPDU_HEADER_LEN",
    "GTPU_PORT",
    "G_PDU",
    "N3_OVERHEAD",
    "PDU_TYPE_DL",
    "PDU_TYPE_UL",
    "GtpError",
    "GtpMessage",
    "check_qfi",
    "decode",
    "echo_request",
    "echo_response",
    "encode_gpdu",
]
