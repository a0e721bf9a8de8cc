"""Does this kernel take a netem qdisc? What the `auto` link backend asks at run time (`tc` where
it does, `userspace` where it does not): tried once per process in a sandbox, then cached."""

from __future__ import annotations

import threading

from testbed.check.sandbox import probe_qdisc

_netem: tuple[bool, str] | None = None
_netem_lock = threading.Lock()


def netem_status() -> tuple[bool, str]:
    """(works, detail) for sch_netem, tried once per process and cached."""
    global _netem
    with _netem_lock:
        if _netem is None:
            _netem = probe_qdisc("netem")
        return _netem


def remember_netem(ok: bool, detail: str) -> None:
    """Cache what a full preflight found for netem, so a later `auto` choice does not probe."""
    global _netem
    with _netem_lock:
        _netem = (ok, detail)


def netem_available() -> bool:
    """Does this kernel take a netem qdisc? Decides the `auto` backend (cached per process)."""
    return netem_status()[0]
