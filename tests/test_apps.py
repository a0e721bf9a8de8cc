"""The pieces of `testbed.apps` that need no namespace: what counts as a listening port, and a
log readiness check that sees a line only once it is whole (issue #18)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

from testbed.apps import AppProcess, Readiness, listening
from testbed.scenario.model import App, Ready


def test_listening_reads_tcp_listen_and_udp_bound_sockets_of_a_process() -> None:
    tcp = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    udp = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
    conn = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        tcp.bind(("127.0.0.1", 0))
        bound_only = tcp.getsockname()[1]
        assert not listening(os.getpid(), bound_only, "tcp")  # bound, not yet listening
        tcp.listen()
        udp.bind(("::1", 0))
        assert listening(os.getpid(), bound_only, "tcp")
        assert listening(os.getpid(), udp.getsockname()[1], "udp")  # found in udp6
        assert not listening(os.getpid(), udp.getsockname()[1], "tcp")
        conn.connect(("127.0.0.1", bound_only))  # an established socket is not a listener
        assert not listening(os.getpid(), conn.getsockname()[1], "tcp")
    finally:
        for s in (tcp, udp, conn):
            s.close()


def test_a_log_line_counts_once_whole_and_later_lines_are_read_from_where_it_stopped(
    tmp_path: Path,
) -> None:
    log = tmp_path / "app.x.log"
    app = App("x", "av1", ("python",), ready=Ready("log", r"^listening on \d+$", 5.0))
    proc = AppProcess(app, log)
    readiness = Readiness(proc, lambda _: subprocess.Popen([sys.executable, "-c", "pass"]))
    assert readiness.check() is False  # no log yet
    log.write_text("starting\nlistening on 5")
    # The partial last line is matched as it stands only if it already matches in full.
    assert readiness.check() is True
    readiness2 = Readiness(proc, lambda _: subprocess.Popen([sys.executable, "-c", "pass"]))
    log.write_text("starting\nlistening on ")
    assert readiness2.check() is False
    with open(log, "a") as f:
        f.write("not a number\n")
    assert readiness2.check() is False
    with open(log, "a") as f:
        f.write("listening on 8080\n")
    assert readiness2.check() is True
