"""A pcapng writer for the packets an emulated link carries (Wireshark and tshark read it).

    with PcapngWriter(path) as cap:
        up = cap.interface("av1-gnb1 uplink")
        cap.packet(up, ip_packet, t_ns, direction="outbound", comment="first after the outage")
        cap.statistics(up, t_ns, received=1, dropped=3)

One file is one section (Section Header Block); each `interface` is an Interface Description
Block with link type RAW (101: the packet starts at its IPv4/IPv6 header, as a TUN device hands
it over) and nanosecond timestamps; each packet an Enhanced Packet Block whose flags carry the
direction; `statistics` an Interface Statistics Block (packets seen and dropped). The file is
written to `<path>.part` and renamed on `close()`, so a reader never sees a half-written
capture under the final name (pcapng spec: IETF draft-ietf-opsawg-pcapng).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import BinaryIO, Literal

LINKTYPE_RAW = 101
_SHB, _IDB, _EPB, _ISB = 0x0A0D0D0A, 0x00000001, 0x00000006, 0x00000005
_BYTE_ORDER_MAGIC = 0x1A2B3C4D
_OPT_END, _OPT_COMMENT = 0, 1
_IF_NAME, _IF_TSRESOL = 2, 9
_EPB_FLAGS = 2
_ISB_IFRECV, _ISB_IFDROP = 4, 5
_DIRECTION = {"inbound": 1, "outbound": 2}


def _option(code: int, value: bytes) -> bytes:
    pad = (-len(value)) % 4
    return struct.pack("<HH", code, len(value)) + value + b"\0" * pad


def _block(kind: int, body: bytes) -> bytes:
    total = 12 + len(body)
    return struct.pack("<II", kind, total) + body + struct.pack("<I", total)


class PcapngWriter:
    """One pcapng file being written; a context manager (see the module doc)."""

    def __init__(self, path: str | os.PathLike[str], application: str = "edgeloc-testbed") -> None:
        self.path = Path(path)
        self._part = self.path.with_name(self.path.name + ".part")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: BinaryIO | None = open(self._part, "wb")  # noqa: SIM115 (closed by close())
        self._interfaces = 0
        self.packets = 0
        body = struct.pack("<IHHq", _BYTE_ORDER_MAGIC, 1, 0, -1)
        body += _option(4, application.encode()) + _option(_OPT_END, b"")  # shb_userappl
        self._f.write(_block(_SHB, body))

    def interface(self, name: str, linktype: int = LINKTYPE_RAW, snaplen: int = 0) -> int:
        """A new interface (its id, for `packet`): `name` shows as the capture interface."""
        f = self._file()
        body = struct.pack("<HHI", linktype, 0, snaplen)
        body += _option(_IF_NAME, name.encode()) + _option(_IF_TSRESOL, bytes((9,)))
        body += _option(_OPT_END, b"")
        f.write(_block(_IDB, body))
        self._interfaces += 1
        return self._interfaces - 1

    def packet(
        self,
        interface: int,
        data: bytes,
        t_ns: int,
        direction: Literal["inbound", "outbound"] | None = None,
        comment: str | None = None,
        original_length: int | None = None,
    ) -> None:
        """One packet seen at `t_ns` (ns since the epoch) on `interface`."""
        f = self._file()
        if not 0 <= interface < self._interfaces:
            raise ValueError(f"no interface {interface} in {self.path} (have {self._interfaces})")
        opts = b""
        if direction is not None:
            opts += _option(_EPB_FLAGS, struct.pack("<I", _DIRECTION[direction]))
        if comment:
            opts += _option(_OPT_COMMENT, comment.encode())
        if opts:
            opts += _option(_OPT_END, b"")
        pad = (-len(data)) % 4
        orig = len(data) if original_length is None else original_length
        body = struct.pack("<IIIII", interface, t_ns >> 32, t_ns & 0xFFFFFFFF, len(data), orig)
        f.write(_block(_EPB, body + data + b"\0" * pad + opts))
        self.packets += 1

    def statistics(self, interface: int, t_ns: int, received: int, dropped: int) -> None:
        """An Interface Statistics Block: `received` packets seen and `dropped` ones (what the
        link's impairments dropped before they could be captured), as capinfos shows them."""
        f = self._file()
        body = struct.pack("<III", interface, t_ns >> 32, t_ns & 0xFFFFFFFF)
        body += _option(_ISB_IFRECV, struct.pack("<Q", received))
        body += _option(_ISB_IFDROP, struct.pack("<Q", dropped))
        body += _option(_OPT_END, b"")
        f.write(_block(_ISB, body))

    def _file(self) -> BinaryIO:
        if self._f is None:
            raise ValueError(f"capture {self.path} is closed")
        return self._f

    def close(self) -> None:
        """Finish the file and give it its final name."""
        if self._f is not None:
            self._f.close()
            self._f = None
            os.replace(self._part, self.path)

    def abort(self) -> None:
        """Drop the half-written file (nothing is left under either name)."""
        if self._f is not None:
            self._f.close()
            self._f = None
            self._part.unlink(missing_ok=True)

    def __enter__(self) -> PcapngWriter:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


__all__ = ["LINKTYPE_RAW", "PcapngWriter"]
