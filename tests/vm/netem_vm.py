"""A throwaway qemu VM with a stock Debian kernel, for testing the tc backend where the host
kernel has no sch_netem.

    sudo .venv/bin/python -m tests.vm.netem_vm            # run tests/test_tc_root.py in the guest
    sudo .venv/bin/python -m tests.vm.netem_vm -- -k netem # pytest arguments after `--`
    sudo .venv/bin/python -m tests.vm.netem_vm --run 'python tests/bench/bench_links.py --quick'

What the guest is: the kernel of Debian's `linux-image-amd64` (installed on the host with
`make sysdeps`; the host never boots it), an initramfs built here at run time (busybox-static
and the package's own virtio/9p/qdisc modules, in a temporary directory), and the host's `/`
mounted read-only over virtio-9p. So the guest runs the host's exact Python, `.venv` and
checkout; everything it writes goes to guest-private tmpfs, and results come back through a
second, writable 9p share of a host temporary directory (`/run/vmout` in the guest). The
checkout (and the venv, when it lies outside the checkout) is also exported on its own and
mounted at its host path after the tmpfs, so a checkout under /tmp or /run is seen too.

The VM has no network card (`-nic none`): the tests build namespaces inside the guest, so no
host network state is touched. It never outlives its caller: qemu gets SIGKILL when the
calling process dies (PR_SET_PDEATHSIG) and when the time limit passes, and the guest powers
off when its job ends. KVM is used when /dev/kvm works, TCG otherwise; a KVM guest that
prints nothing for `KVM_SILENCE_S` before its init runs is killed and the VM boots again
under TCG, saying so (a /dev/kvm can run the probe's firmware and still not boot a kernel).

`make sysdeps` (run by `make test`) installs qemu-system-x86, linux-image-amd64 and
busybox-static from Debian; without them the test fails and says what to install. Under TCG the
emulated CPU is many times slower (`make bench BENCH=netem_vm` prints the slowdown), so the
guest's high-rate and timeline rows say nothing about fidelity. `make bench BENCH=netem_vm`
prints the link fidelity table measured in the guest, with the guest's overhead (boot, CPU
slowdown, timer lateness, path RTT).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
GUEST_INIT = HERE / "guest_init.sh"

#: What `make sysdeps` installs from Debian for the VM.
DEBIAN_PACKAGES = ("qemu-system-x86", "linux-image-amd64", "busybox-static")
INSTALL_HINT = (
    "run `sudo make sysdeps` (apt-get install --no-install-recommends "
    + " ".join(DEBIAN_PACKAGES)
    + ")"
)

#: Modules the guest loads before it can see the host (virtio PCI transport and 9p), then
#: the ones the tc tests and `testbed check` use. Their dependencies come from modules.dep.
TRANSPORT_MODULES = ("virtio_pci", "9pnet_virtio", "9p")
TEST_MODULES = (
    "veth",
    "tun",
    "ifb",
    "sch_htb",
    "sch_tbf",
    "sch_netem",
    "sch_ingress",
    "act_mirred",
    "cls_u32",
)

#: Console lines the guest init prints (tests/vm/guest_init.sh).
BOOTED, READY, EXIT, FAIL = (
    "EDGELOC-VM-BOOTED",
    "EDGELOC-VM-READY",
    "EDGELOC-VM-EXIT",
    "EDGELOC-VM-FAIL",
)

PR_SET_PDEATHSIG = 1
#: Where guest_init.sh mounts guest-private tmpfs over the host's read-only root.
GUEST_TMPFS = ("/tmp", "/var/tmp", "/run", "/dev/shm")
#: Host directories exported on their own (9p tags `bind0`, `bind1`, ...), listed one per line
#: in this file of the output share; guest_init.sh mounts each at its host path over the tmpfs.
BINDS_FILE = "binds"
#: Seconds a KVM guest may print nothing before its init runs: under KVM the kernel reaches
#: init in a second or two, so a silent console means the guest is not booting and waiting
#: for the whole time limit would only hide that. TCG gets no such limit (it boots slowly).
KVM_SILENCE_S = 20.0


class VmUnavailable(RuntimeError):
    """This host cannot boot the test VM; the message says what is missing and how to fix it."""


# ---- what the VM is made of ---------------------------------------------------------------------


@dataclass(frozen=True)
class GuestKernel:
    """A kernel image from a Debian `linux-image-*` package and its module tree."""

    version: str
    image: Path
    modules: Path  # /lib/modules/<version>

    def module_paths(self, names: Sequence[str]) -> list[str]:
        """Paths (relative to `modules`) of `names` and what they need, dependencies first."""
        deps: dict[str, list[str]] = {}
        by_name: dict[str, str] = {}
        for line in (self.modules / "modules.dep").read_text().splitlines():
            path, _, rest = line.partition(":")
            deps[path] = rest.split()
            by_name[module_name(path)] = path
        order: list[str] = []

        def visit(path: str, chain: tuple[str, ...]) -> None:
            if path in order:
                return
            if path in chain:
                raise VmUnavailable(f"{self.modules}/modules.dep has a dependency cycle at {path}")
            for dep in deps.get(path, []):
                visit(dep, (*chain, path))
            order.append(path)

        for name in names:
            if name not in by_name:
                raise VmUnavailable(
                    f"kernel {self.version} has no module {name} (not in {self.modules}/"
                    "modules.dep): the VM needs Debian's linux-image-amd64"
                )
            visit(by_name[name], ())
        return order


def module_name(path: str) -> str:
    """`kernel/net/sched/sch_netem.ko(.xz)` -> `sch_netem` (modules.dep names, `-` as `_`)."""
    base = path.rsplit("/", 1)[-1]
    return re.sub(r"\.ko(\.(xz|zst|gz))?$", "", base).replace("-", "_")


def _version_key(version: str) -> list[int | str]:
    return [int(p) if p.isdigit() else p for p in re.split(r"[.-]", version)]


def find_kernel(boot: Path = Path("/boot"), lib: Path = Path("/lib/modules")) -> GuestKernel:
    """The newest installed kernel with every module the VM needs, as plain `.ko` files.

    Debian's `linux-image-amd64` builds all of them as modules; a kernel built without them
    (or with them built in, which the initramfs cannot tell apart from missing) is passed over.
    """
    seen: list[str] = []
    for image in sorted(boot.glob("vmlinuz-*"), key=lambda p: _version_key(p.name), reverse=True):
        version = image.name.removeprefix("vmlinuz-")
        kernel = GuestKernel(version, image, lib / version)
        dep = kernel.modules / "modules.dep"
        if not dep.is_file():
            seen.append(f"{image} (no {dep})")
            continue
        try:
            paths = kernel.module_paths(TRANSPORT_MODULES + TEST_MODULES)
        except VmUnavailable as err:
            seen.append(f"{image} ({err})")
            continue
        if any(not p.endswith(".ko") for p in paths):
            seen.append(f"{image} (compressed modules: the busybox initramfs loads plain .ko)")
            continue
        if not os.access(image, os.R_OK):
            seen.append(f"{image} (not readable)")
            continue
        return kernel
    found = "; ".join(seen) if seen else f"no {boot}/vmlinuz-*"
    raise VmUnavailable(f"no usable guest kernel ({found}): {INSTALL_HINT}")


def find_qemu() -> Path:
    qemu = shutil.which("qemu-system-x86_64")
    if qemu is None:
        raise VmUnavailable(f"qemu-system-x86_64 is not installed: {INSTALL_HINT}")
    return Path(qemu)


def _is_static_elf(path: Path) -> bool:
    """True when `path` is an ELF executable with no PT_INTERP (no dynamic loader)."""
    data = path.read_bytes()
    if data[:4] != b"\x7fELF" or data[4] != 2:  # 64-bit only: the guest is x86-64
        return False
    phoff = int.from_bytes(data[0x20:0x28], "little")
    phentsize = int.from_bytes(data[0x36:0x38], "little")
    phnum = int.from_bytes(data[0x38:0x3A], "little")
    for i in range(phnum):
        off = phoff + i * phentsize
        if int.from_bytes(data[off : off + 4], "little") == 3:  # PT_INTERP
            return False
    return True


def find_busybox() -> Path:
    """busybox-static's binary: PID 1 of the initramfs must run before any library is there."""
    for candidate in ("/bin/busybox", "/usr/bin/busybox"):
        path = Path(candidate)
        if path.is_file() and _is_static_elf(path):
            return path
    raise VmUnavailable(f"no statically linked busybox (package busybox-static): {INSTALL_HINT}")


def choose_accel(qemu: Path) -> str:
    """`kvm` when qemu can run a guest under KVM here, else `tcg` (EDGELOC_VM_ACCEL overrides)."""
    forced = os.environ.get("EDGELOC_VM_ACCEL")
    if forced in ("kvm", "tcg"):
        return forced
    return "kvm" if kvm_usable(qemu) else "tcg"


def kvm_usable(qemu: Path) -> bool:
    """Whether qemu can run a vCPU under KVM here with the CPU model the VM uses.

    Asked of qemu itself: a 64 KiB firmware whose reset vector writes 0x42 to an
    isa-debug-exit port, so qemu exits with status 0x42 * 2 + 1 = 133 when the vCPU really ran
    (0.1 s). A /dev/kvm that opens but cannot run this CPU (here: a PVM-only KVM refuses an MSR
    for `-cpu host`, and qemu aborts) answers anything else.
    """
    if not os.access("/dev/kvm", os.R_OK | os.W_OK):
        return False
    firmware = bytearray(b"\xf4" * 65536)  # hlt everywhere
    firmware[0xFFF0:0xFFF5] = bytes([0xB0, 0x42, 0xE6, 0xF4, 0xF4])  # mov al,0x42; out 0xf4,al; hlt
    with tempfile.TemporaryDirectory(prefix="edgeloc-kvm-") as d:
        bios = Path(d) / "probe.bin"
        bios.write_bytes(firmware)
        try:
            probe = subprocess.run(
                [
                    *(str(qemu), "-accel", "kvm", "-cpu", "host", "-machine", "pc"),
                    *("-nodefaults", "-display", "none", "-monitor", "none", "-serial", "none"),
                    *("-bios", str(bios), "-device", "isa-debug-exit,iobase=0xf4,iosize=0x04"),
                ],
                capture_output=True,
                timeout=20,
                preexec_fn=_die_with_parent,
            )
        except (OSError, subprocess.TimeoutExpired):
            return False
    return probe.returncode == 0x42 * 2 + 1


# ---- initramfs -----------------------------------------------------------------------------------


def _cpio_entry(name: str, mode: int, data: bytes = b"", ino: int = 0) -> bytes:
    """One member of a `newc` cpio archive (the format the kernel unpacks as its initramfs)."""
    namez = name.encode() + b"\0"
    fields = [ino, mode, 0, 0, 1, 0, len(data), 0, 0, 0, 0, len(namez), 0]
    header = b"070701" + b"".join(f"{v:08x}".encode() for v in fields)
    pad_name = b"\0" * ((4 - (len(header) + len(namez)) % 4) % 4)
    pad_data = b"\0" * ((4 - len(data) % 4) % 4)
    return header + namez + pad_name + data + pad_data


def build_initramfs(kernel: GuestKernel, busybox: Path, out: Path) -> Path:
    """Write the guest's initramfs (uncompressed newc cpio) to `out`; returns `out`.

    Holds /init (tests/vm/guest_init.sh), /bin/busybox, the modules in load order under
    their /lib/modules path and /modules.order listing them.
    """
    modules = kernel.module_paths(TRANSPORT_MODULES + TEST_MODULES)
    prefix = f"lib/modules/{kernel.version}"
    dirs: list[str] = ["bin", "lib", "lib/modules", prefix]
    for path in modules:
        parts = path.split("/")[:-1]
        for i in range(1, len(parts) + 1):
            d = f"{prefix}/{'/'.join(parts[:i])}"
            if d not in dirs:
                dirs.append(d)
    members: list[tuple[str, int, bytes]] = [(d, 0o040755, b"") for d in dirs]
    members.append(("init", 0o100755, GUEST_INIT.read_bytes()))
    members.append(("bin/busybox", 0o100755, busybox.read_bytes()))
    members.append(
        ("modules.order", 0o100644, "".join(f"{prefix}/{m}\n" for m in modules).encode())
    )
    members += [(f"{prefix}/{m}", 0o100644, (kernel.modules / m).read_bytes()) for m in modules]
    with out.open("wb") as f:
        for ino, (name, mode, data) in enumerate(members, start=1):
            f.write(_cpio_entry(name, mode, data, ino))
        f.write(_cpio_entry("TRAILER!!!", 0))
    return out


# ---- running the guest -------------------------------------------------------------------------


@dataclass
class GuestRun:
    """What one VM run produced."""

    rc: int | None  # the job's exit status; None when the guest never reported one
    console: str
    out: Path  # the host directory the guest wrote to (`/run/vmout` inside)
    accel: str
    wall_s: float  # qemu start to qemu exit
    boot_s: float | None = None  # qemu start until the guest init ran (kernel + initramfs)
    ready_s: float | None = None  # qemu start until the host root was mounted in the guest
    failure: str | None = None  # why the run did not finish, when it did not
    timed_out: bool = False
    timings: dict[str, float] = field(default_factory=dict)
    silent: bool = False  # killed for printing nothing before its init ran (see KVM_SILENCE_S)
    notes: list[str] = field(default_factory=list)  # e.g. why KVM was given up for TCG

    @property
    def ok(self) -> bool:
        return self.rc == 0 and self.failure is None


def _die_with_parent() -> None:
    # Runs in the qemu child before exec: the kernel SIGKILLs qemu if the test process dies,
    # so even a `kill -9` of pytest leaves no VM behind.
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() == 1:  # the parent died before prctl took effect
        os._exit(1)


def _job_script(command: str, env: dict[str, str], checkout: Path) -> str:
    exports = "".join(f"export {k}={shlex.quote(v)}\n" for k, v in env.items())
    return (
        "#!/bin/sh\n"
        "# written by tests/vm/netem_vm.py; runs chrooted into the host's read-only root\n"
        f"{exports}"
        'mkdir -p "$HOME"\n'
        f"cd {shlex.quote(str(checkout))} || exit 97\n"
        f"{command}\n"
    )


def _bootstrap_env() -> dict[str, str]:
    """The environment the ROS wheels' .pth bootstrapper gives this process, for the guest.

    Without it every Python start in the venv re-executes itself once to set LD_LIBRARY_PATH:
    a second interpreter start, which costs seconds in an emulated guest. The guest runs the
    same venv at the same paths, so this process's values are the right ones there too.
    """
    keys = ("LD_LIBRARY_PATH", "_ROS_WHEELS_BOOTSTRAP_COMPLETE")
    return {k: os.environ[k] for k in keys if k in os.environ}


def venv_python() -> Path:
    """The interpreter the guest runs: this one (the project's .venv), by its venv path."""
    return Path(sys.executable) if sys.prefix != sys.base_prefix else REPO / ".venv/bin/python"


def guest_binds(checkout: Path, python: Path) -> list[Path]:
    """Host directories the guest mounts at their own paths on top of its tmpfs: the checkout,
    and the venv holding `python` unless it is inside the checkout.

    The host root alone is not enough: the guest's tmpfs on /tmp, /run ... hides whatever the
    host keeps there, and a checkout under /tmp is an ordinary place for a clone.
    """
    binds = [checkout]
    venv = python.parent.parent  # <venv>/bin/python, by its venv path (not resolved)
    if (venv / "pyvenv.cfg").is_file() and venv != checkout and checkout not in venv.parents:
        binds.append(venv)
    return binds


def _virtfs_args(binds: Sequence[Path], out: Path) -> list[str]:
    args = [
        "-virtfs",
        "local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap",
        "-virtfs",
        f"local,path={out},mount_tag=out,security_model=none",
    ]
    for i, path in enumerate(binds):
        if "," in str(path) or "\n" in str(path):
            # qemu's option parser splits at commas; guest_init.sh reads one path per line
            raise VmUnavailable(f"cannot export {path!r} to the guest (a comma or newline in it)")
        args += [
            "-virtfs",
            f"local,path={path},mount_tag=bind{i},security_model=none,readonly=on,multidevs=remap",
        ]
    return args


def _accel_args(accel: str) -> list[str]:
    if accel == "kvm":
        return ["-accel", "kvm", "-cpu", "host"]
    # multi-threaded TCG: one host thread per vCPU
    return ["-accel", "tcg,thread=multi", "-cpu", "max"]


@contextlib.contextmanager
def _workdir(keep: Path | None) -> Iterator[Path]:
    if keep is not None:
        keep.mkdir(parents=True, exist_ok=True)
        yield keep
        return
    with tempfile.TemporaryDirectory(prefix="edgeloc-vm-") as d:
        yield Path(d)


def run_in_guest(
    command: str,
    *,
    timeout_s: float = 900,
    memory_mib: int = 2048,
    cpus: int = 2,
    echo: bool = False,
    workdir: Path | None = None,
    env: dict[str, str] | None = None,
    checkout: Path = REPO,
) -> GuestRun:
    """Boot the VM, run the shell `command` in the repo checkout inside it, power off.

    `command` runs as root in the guest with the project's venv first on PATH; files it writes
    under $VMOUT come back in `GuestRun.out` (only valid inside a kept `workdir`, else the
    caller must read them before this returns: pass `workdir` to keep them). `checkout` is
    where the command runs (this checkout; tests pass another directory). Raises
    VmUnavailable when the host lacks qemu, busybox-static or the Debian kernel.
    """
    qemu, busybox, kernel = find_qemu(), find_busybox(), find_kernel()
    if not GUEST_INIT.is_file():
        raise VmUnavailable(f"{GUEST_INIT} is missing from the checkout")
    python = venv_python()
    with _workdir(workdir) as work:
        out = work / "out"
        out.mkdir(exist_ok=True)
        initrd = build_initramfs(kernel, busybox, work / "initramfs.cpio")
        guest_env = {
            "PATH": f"{python.parent}:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin",
            "HOME": "/tmp/home",
            "VMOUT": "/run/vmout",
            "EDGELOC_IN_VM": "1",
            # the checkout is read-only in the guest: no bytecode caches, no pytest cache
            "PYTHONDONTWRITEBYTECODE": "1",
            "PYTHONUNBUFFERED": "1",
            "LANG": "C.UTF-8",
            **_bootstrap_env(),
            **(env or {}),
        }
        (out / "job.sh").write_text(_job_script(command, guest_env, checkout))
        binds = guest_binds(checkout, python)
        (out / BINDS_FILE).write_text("".join(f"{b}\n" for b in binds))
        accel = choose_accel(qemu)
        # KVM that was not asked for by name may fall back to TCG; a forced one fails fast
        fallback = accel == "kvm" and os.environ.get("EDGELOC_VM_ACCEL") != "kvm"
        args = [
            str(qemu),
            "-nodefaults",
            "-no-user-config",
            "-no-reboot",
            "-display",
            "none",
            "-monitor",
            "none",
            "-serial",
            "stdio",
            "-nic",
            "none",
            "-m",
            str(memory_mib),
            "-smp",
            str(cpus),
            "-kernel",
            str(kernel.image),
            "-initrd",
            str(initrd),
            "-append",
            # panic=-1 + -no-reboot: a guest whose init dies makes qemu exit at once;
            # tsc=reliable: no clocksource watchdog switching clocks when TCG runs late
            "console=ttyS0 panic=-1 quiet loglevel=4 rdinit=/init tsc=reliable",
            *_virtfs_args(binds, out),
        ]
        accels = [accel, "tcg"] if fallback else [accel]
        return boot_guest(
            lambda a: [*args, *_accel_args(a)], accels, out, timeout_s, echo, KVM_SILENCE_S
        )


def boot_guest(
    argv_for: Callable[[str], list[str]],
    accels: Sequence[str],
    out: Path,
    timeout_s: float,
    echo: bool,
    kvm_silence_s: float = KVM_SILENCE_S,
) -> GuestRun:
    """Run qemu (`argv_for(accel)`) under each accelerator of `accels` in turn until one is not
    silent: a KVM guest that prints nothing for `kvm_silence_s` before its init runs is killed
    and the next accelerator is tried, with a note saying so (printed, in `GuestRun.notes` and
    in console.log). `timeout_s` covers all attempts together."""
    start = time.monotonic()
    (out.parent / "console.log").write_text("")  # the attempts append to it
    notes: list[str] = []
    for i, accel in enumerate(accels):
        left = max(1.0, timeout_s - (time.monotonic() - start))
        silence = kvm_silence_s if accel == "kvm" else None
        run = _supervise(argv_for(accel), out, accel, left, echo, silence)
        if not run.silent or i == len(accels) - 1:
            run.notes[:0] = notes
            return run
        note = (
            f"the {accel} guest printed nothing for {kvm_silence_s:g} s before its init ran "
            f"(killed after {run.wall_s:.1f} s): booting it again under {accels[i + 1]}"
        )
        print(f"[vm] {note}", file=sys.stderr, flush=True)
        with (out.parent / "console.log").open("a") as log:
            log.write(f"[vm] {note}\n")
        notes.append(note)
    raise AssertionError("no accelerator to boot the guest with")  # accels was empty


def _supervise(
    args: list[str],
    out: Path,
    accel: str,
    timeout_s: float,
    echo: bool,
    silence_s: float | None = None,
) -> GuestRun:
    lines: list[str] = []
    marks: dict[str, float] = {}
    start = time.monotonic()
    last_output = [start]  # the reader thread moves it on with every console line
    proc = subprocess.Popen(
        args,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        preexec_fn=_die_with_parent,
        start_new_session=True,  # a Ctrl-C aimed at the test run reaches qemu through us only
    )
    assert proc.stdout is not None

    def reader() -> None:
        assert proc.stdout is not None
        # console.log next to the output share: to follow a long run (`tail -f`) and to read
        # after a failure, when `workdir` is kept
        with (out.parent / "console.log").open("a") as log:
            log.write(f"[vm] qemu -accel {accel}\n")
            for raw in proc.stdout:
                last_output[0] = time.monotonic()
                line = raw.decode(errors="replace").rstrip("\r\n")
                lines.append(line)
                log.write(line + "\n")
                log.flush()
                for mark in (BOOTED, READY, EXIT, FAIL):
                    if line.startswith(mark) and mark not in marks:
                        marks[mark] = time.monotonic() - start
                if echo:
                    print(f"[vm] {line}", file=sys.stderr, flush=True)

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    timed_out = silent = False
    deadline = start + timeout_s
    try:
        while proc.poll() is None:
            now = time.monotonic()
            if now >= deadline:
                timed_out = True
                break
            if silence_s is not None and BOOTED not in marks and now - last_output[0] > silence_s:
                silent = True
                break
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=min(0.2, max(0.01, deadline - now)))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    thread.join(timeout=5)
    wall = time.monotonic() - start
    console = "\n".join(lines)
    rc = _exit_status(console, out)
    failure = None
    if silent:
        failure = (
            f"the guest ({accel}) printed nothing for {silence_s:g} s before its init ran "
            "and was killed"
        )
    elif timed_out:
        failure = f"the VM did not finish within {timeout_s:.0f} s and was killed"
    elif rc is None:
        fail_line = next((ln for ln in lines if ln.startswith(FAIL)), None)
        failure = (
            f"guest init failed: {fail_line.removeprefix(FAIL).strip()}"
            if fail_line
            else f"qemu exited ({proc.returncode}) without the guest reporting a result"
        )
    return GuestRun(
        rc=rc,
        console=console,
        out=out,
        accel=accel,
        wall_s=wall,
        boot_s=marks.get(BOOTED),
        ready_s=marks.get(READY),
        failure=failure,
        timed_out=timed_out,
        timings=marks,
        silent=silent,
    )


def _exit_status(console: str, out: Path) -> int | None:
    match = re.search(rf"^{EXIT} (\d+)", console, re.MULTILINE)
    if match:
        return int(match.group(1))
    rc_file = out / "rc"
    if rc_file.is_file() and rc_file.read_text().strip().isdigit():
        return int(rc_file.read_text().strip())
    return None


def pytest_command(pytest_args: Sequence[str]) -> str:
    """The guest's pytest line: junit XML to $VMOUT, no cache writes into the read-only tree.

    Plugin auto-loading is off: it reads the metadata of every distribution in the venv (ROS,
    torch: hundreds), half of pytest's start-up in the guest. The one plugin the tests use,
    pytest-rerunfailures (conftest's `flaky` marker), is loaded by name.
    """
    args = [
        "--color=no",
        "-p",
        "pytest_rerunfailures",
        "-p",
        "no:cacheprovider",
        "--junitxml=/run/vmout/junit.xml",
        *pytest_args,
    ]
    return (
        f"PYTEST_DISABLE_PLUGIN_AUTOLOAD=1 {shlex.quote(str(venv_python()))} -m pytest "
        + " ".join(map(shlex.quote, args))
    )


#: What the guest runs by default: every test that needs sch_netem. The tc tests without netem
#: (HTB rates, IFB, shape/clear, the netem-free dry run, errors) run on the host itself in
#: `make test`; `python -m tests.vm.netem_vm -- tests/test_tc_root.py` runs them all in the VM.
DEFAULT_PYTEST = (
    "-v",
    "-s",
    "-rsR",
    "-k",
    "netem",
    "tests/test_tc_root.py",
    "tests/vm/guest_checks.py",
)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run", help="a shell command to run in the guest instead of pytest")
    parser.add_argument(
        "--timeout", type=float, default=900, help="seconds before the VM is killed"
    )
    parser.add_argument("--memory", type=int, default=2048, help="guest memory in MiB")
    parser.add_argument("--keep", type=Path, help="keep the initramfs and guest output here")
    parser.add_argument("pytest_args", nargs="*", help="pytest arguments (after `--`)")
    args = parser.parse_args(argv)
    if os.geteuid() != 0:
        print("netem_vm needs root (qemu's 9p export of / and namespaces in the guest)")
        return 3
    command = args.run or pytest_command(args.pytest_args or DEFAULT_PYTEST)
    try:
        run = run_in_guest(
            command, timeout_s=args.timeout, memory_mib=args.memory, echo=True, workdir=args.keep
        )
    except VmUnavailable as err:
        print(f"cannot run the VM: {err}", file=sys.stderr)
        return 3
    boot = f"{run.boot_s:.1f}" if run.boot_s is not None else "?"
    ready = f"{run.ready_s:.1f}" if run.ready_s is not None else "?"
    for note in run.notes:
        print(f"VM: {note}", file=sys.stderr)
    print(
        f"VM ({run.accel}): init at {boot} s, host root mounted at {ready} s, "
        f"powered off at {run.wall_s:.1f} s; job exit {run.rc}"
        + (f"; {run.failure}" if run.failure else ""),
        file=sys.stderr,
    )
    return 0 if run.ok else 1


if __name__ == "__main__":
    sys.exit(main())
