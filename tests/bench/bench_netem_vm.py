"""Fidelity of the `tc` backend (real netem + HTB), measured inside the throwaway VM.

    sudo .venv/bin/python tests/bench/bench_netem_vm.py [--quick]

Where the host kernel has no sch_netem, `make bench` cannot measure the tc backend on the
host; this boots the VM of `tests.vm.netem_vm` (Debian's kernel, the host's checkout and venv
read-only over 9p) and runs tests/bench/bench_links.py in it, so the rows are the very rows of
the userspace backend's table, here on the backend `auto` picks in the guest (tc). Where the
host has sch_netem, bench_links measures the tc backend directly and this prints that.

The guest's overhead is printed with it: boot time, and how much slower the guest runs the same
Python loop and the same no-delay UDP round trip through a veth pair than the host does (TCG
emulates every guest instruction; on 2 shared cores the guest also competes with the host).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from testbed.check import netem_status  # noqa: E402
from tests.vm.netem_vm import VmUnavailable, run_in_guest, venv_python  # noqa: E402

#: A fixed amount of pure-Python work (its time on the host and in the guest gives the
#: guest's CPU slowdown), then how late 2 ms sleeps wake up (the timer lateness that netem's
#: own hrtimer sees too). Printed as JSON {"loop_s": ..., "oversleep_ms": [...]}.
CPU_PROBE = """
import json, time
t = time.perf_counter(); x = 0
for i in range(3_000_000):
    x += i * i % 7
loop = time.perf_counter() - t
over = []
for _ in range(200):
    t = time.perf_counter(); time.sleep(0.002); over.append((time.perf_counter() - t - 0.002) * 1e3)
print(json.dumps({"loop_s": loop, "oversleep_ms": over}))
"""

#: The no-delay round trip through a veth pair between two namespaces (UDP, Python on both
#: ends): what the path costs before any emulation. Printed as JSON {"rtt_ms": [...]}.
RTT_PROBE = """
import json, secrets, socket, subprocess, sys, time
tag = secrets.token_hex(3); a, b = f"elvm-{tag}-a", f"elvm-{tag}-b"
def sh(*args): subprocess.run(args, check=True)
sh("ip", "netns", "add", a); sh("ip", "netns", "add", b)
try:
    sh("ip", "-n", a, "link", "add", "v0", "type", "veth", "peer", "name", "v1", "netns", b)
    sh("ip", "-n", a, "addr", "add", "10.77.0.1/24", "dev", "v0")
    sh("ip", "-n", b, "addr", "add", "10.77.0.2/24", "dev", "v1")
    sh("ip", "-n", a, "link", "set", "v0", "up"); sh("ip", "-n", b, "link", "set", "v1", "up")
    echo = subprocess.Popen(["ip", "netns", "exec", b, sys.executable, "-c",
        "import socket; s=socket.socket(2,2); s.bind(('10.77.0.2',9)); s.settimeout(5)\\n"
        "while True:\\n d,x=s.recvfrom(99); s.sendto(d,x)"])
    out = subprocess.run(["ip", "netns", "exec", a, sys.executable, "-c",
        "import json,socket,time\\ns=socket.socket(2,2); s.settimeout(1); r=[]\\n"
        "time.sleep(1)\\n"
        "for i in range(300):\\n t=time.perf_counter(); s.sendto(b'x',('10.77.0.2',9))\\n"
        " try: s.recvfrom(99); r.append((time.perf_counter()-t)*1e3)\\n"
        " except OSError: pass\\n time.sleep(0.005)\\n"
        "print(json.dumps(r))"], capture_output=True, text=True, check=True)
    echo.kill(); echo.wait()
    print(json.dumps({"rtt_ms": json.loads(out.stdout)}))
finally:
    sh("ip", "netns", "del", a); sh("ip", "netns", "del", b)
"""


def _host_probe(code: str) -> dict:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _guest_json(out: Path, name: str) -> dict:
    path = out / name
    return json.loads(path.read_text()) if path.is_file() else {}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="bench_links --quick in the guest")
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("bench_netem_vm needs root (qemu's 9p export, namespaces)", file=sys.stderr)
        return 2
    has_netem, detail = netem_status()
    if has_netem:
        print(f"this host's kernel has sch_netem ({detail}): bench_links measures tc directly")
        return 0
    python = str(venv_python())
    quick = " --quick" if args.quick else ""
    # Probes first (an idle guest), then the table. The probe scripts travel in the output
    # share; each writes its JSON next to them.
    job = (
        f"{python} $VMOUT/cpu_probe.py > $VMOUT/cpu.json && "
        f"{python} $VMOUT/rtt_probe.py > $VMOUT/rtt.json && "
        f"{python} tests/bench/bench_links.py{quick}"
    )
    load = os.getloadavg()
    host_probe = _host_probe(CPU_PROBE)
    host_cpu, host_over = host_probe["loop_s"], statistics.median(host_probe["oversleep_ms"])
    host_rtt = statistics.median(_host_probe(RTT_PROBE)["rtt_ms"])
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="edgeloc-vmbench-") as d:
        out = Path(d) / "out"
        out.mkdir()
        (out / "cpu_probe.py").write_text(CPU_PROBE)
        (out / "rtt_probe.py").write_text(RTT_PROBE)
        try:
            run = run_in_guest(job, timeout_s=1500, echo=False, workdir=Path(d))
        except VmUnavailable as err:
            print(f"cannot run the VM: {err}", file=sys.stderr)
            return 3
        guest_probe = _guest_json(run.out, "cpu.json")
        guest_cpu, guest_over = guest_probe.get("loop_s"), guest_probe.get("oversleep_ms") or []
        guest_rtts = _guest_json(run.out, "rtt.json").get("rtt_ms") or []
    # the table bench_links printed in the guest, as it printed it
    lines = run.console.splitlines()
    first = next(
        (i for i, ln in enumerate(lines) if ln.startswith("link fidelity on backend")), None
    )
    if first is None:
        print("\n".join(lines[-60:]))
        print(f"the guest did not print a fidelity table: {run.failure or f'exit {run.rc}'}")
        return 1
    table = [ln for ln in lines[first:] if not ln.startswith("EDGELOC-VM-") and "reboot:" not in ln]
    print("\n".join(table))
    print(
        f"guest overhead (VM accel {run.accel}; host load average {load[0]:.2f} on "
        f"{os.cpu_count()} cores at the start):"
    )
    boot = f"{run.boot_s:.1f} s" if run.boot_s is not None else "?"
    ready = f"{run.ready_s:.1f} s" if run.ready_s is not None else "?"
    print(f"  {'boot: guest init running':<34} {boot}")
    print(f"  {'boot: host root mounted over 9p':<34} {ready}")
    print(
        f"  {'VM wall time, start to power-off':<34} {run.wall_s:.1f} s "
        f"(bench host-side total {time.monotonic() - started:.1f} s)"
    )
    if guest_cpu:
        print(
            f"  {'Python loop (3M iterations)':<34} host {host_cpu:.2f} s, guest "
            f"{guest_cpu:.2f} s: guest {guest_cpu / host_cpu:.1f}x slower"
        )
    if guest_over:
        print(
            f"  {'timer: 2 ms sleep wakes late by':<34} host median {host_over:.3f} ms, "
            f"guest {statistics.median(guest_over):.3f} ms "
            f"(p90 {statistics.quantiles(guest_over, n=10)[-1]:.3f} ms)"
        )
    if guest_rtts:
        g = statistics.median(guest_rtts)
        print(
            f"  {'no-delay UDP RTT over a veth pair':<34} host median {host_rtt:.3f} ms, "
            f"guest {g:.3f} ms (p90 {statistics.quantiles(guest_rtts, n=10)[-1]:.3f} ms)"
        )
    print(
        "  (compare the misses with these figures: a TCP rate above what the emulated CPU moves,\n"
        "   a timeline event applied by Python running as slowly as the loop above, a delay that\n"
        "   includes the guest's late timer wake-ups)"
    )
    # bench_links exits 1 when a figure misses; here the misses are the emulator's, shown above.
    # Only a VM that did not finish its job is a failure of this benchmark.
    return 0 if run.failure is None and run.rc in (0, 1) else 1


if __name__ == "__main__":
    sys.exit(main())
