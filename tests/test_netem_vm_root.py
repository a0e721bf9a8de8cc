"""The tc backend with real netem where this host's kernel has none: inside a throwaway VM.

Boots Debian's stock kernel under qemu (`tests.vm.netem_vm`), with the host's checkout and
.venv mounted read-only over 9p, and runs tests/test_tc_root.py and tests/vm/guest_checks.py
there: real namespaces, netem + HTB + IFB qdiscs applied through our pyroute2 code, real
traffic measured against the profile. Where the host kernel has sch_netem those files run on
the host directly and this test skips. A host without qemu or the kernel package fails here
with what to install (`sudo make sysdeps`): a silent skip would hide an untested backend.
"""

from __future__ import annotations

import shutil
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from testbed.check import netem_status
from tests.vm import netem_vm
from tests.vm.netem_vm import DEFAULT_PYTEST, VmUnavailable, pytest_command, run_in_guest

pytestmark = [pytest.mark.root, pytest.mark.netem_vm, pytest.mark.slow]

#: The one skip allowed in the guest: the test of a kernel *without* netem.
SKIP_OK = "this kernel has sch_netem"
#: netem tests the guest must pass: 6 of tests/test_tc_root.py, 4 of tests/vm/guest_checks.py.
MIN_NETEM_PASSED = 10


def _cases(junit: Path) -> list[tuple[str, str, str]]:
    """(test id, outcome, message) per test of a junit XML report, its last attempt only.

    pytest-rerunfailures writes one <testcase> per attempt; the last one is the outcome.
    """
    last: dict[str, tuple[str, str, str]] = {}
    for case in ET.parse(junit).getroot().iter("testcase"):
        name = f"{case.get('classname')}::{case.get('name')}"
        outcome, message = "passed", ""
        for child in case:
            if child.tag in ("failure", "error", "skipped"):
                outcome, message = child.tag, child.get("message") or ""
                break
        last[name] = (name, outcome, message)
    return list(last.values())


# No reruns (a marker on the function precedes the one conftest appends to the item): a rerun
# would boot the VM again, and the guest's pytest already retries its real-network tests.
@pytest.mark.flaky(reruns=0)
def test_tc_backend_tests_pass_in_a_vm_with_netem(tmp_path: Path) -> None:
    has_netem, detail = netem_status()
    if has_netem:
        pytest.skip(f"this host's kernel has sch_netem ({detail}): tests/test_tc_root.py runs here")
    try:
        run = run_in_guest(pytest_command(DEFAULT_PYTEST), timeout_s=1200, workdir=tmp_path)
    except VmUnavailable as err:
        pytest.fail(f"cannot test the tc backend (host kernel: {detail}): {err}", pytrace=False)
    tail = "\n".join(run.console.splitlines()[-60:])
    junit = run.out / "junit.xml"
    assert run.failure is None, f"{run.failure}\n--- guest console (tail) ---\n{tail}"
    assert junit.is_file(), f"the guest wrote no junit report\n{tail}"
    cases = _cases(junit)
    bad = [c for c in cases if c[1] in ("failure", "error")]
    skipped = [c for c in cases if c[1] == "skipped" and SKIP_OK not in c[2]]
    netem_passed = [c for c in cases if c[1] == "passed" and "netem" in c[0]]
    for note in run.notes:  # e.g. a silent KVM guest given up for TCG
        print(f"VM: {note}")
    print(
        f"VM ({run.accel}): init {run.boot_s} s, root mounted {run.ready_s} s, "
        f"off {run.wall_s:.1f} s; {len(cases)} tests, {len(netem_passed)} netem tests passed"
    )
    assert not bad, f"failed in the guest: {bad}\n{tail}"
    assert not skipped, f"skipped in the guest (netem must run there): {skipped}"
    assert len(netem_passed) >= MIN_NETEM_PASSED, (
        f"only {len(netem_passed)} netem tests passed in the guest: {netem_passed}"
    )
    assert run.rc == 0, f"guest pytest exited {run.rc}\n{tail}"


@pytest.mark.flaky(reruns=0)
def test_a_checkout_under_tmp_is_seen_by_the_guest(tmp_path: Path) -> None:
    """The guest's own tmpfs on /tmp must not hide a checkout that lives there (a fresh
    `git clone` into /tmp is where many people try a project): the runner exports it."""
    has_netem, detail = netem_status()
    if has_netem:
        pytest.skip(f"this host's kernel has sch_netem ({detail}): no VM is booted here")
    checkout = Path(tempfile.mkdtemp(prefix="edgeloc-checkout-", dir="/tmp"))
    try:
        (checkout / "marker.txt").write_text("seen from the guest\n")
        command = 'pwd > "$VMOUT/pwd"; cat marker.txt > "$VMOUT/marker"'
        try:
            run = run_in_guest(command, timeout_s=300, workdir=tmp_path, checkout=checkout)
        except VmUnavailable as err:
            pytest.fail(f"cannot boot the VM (host kernel: {detail}): {err}", pytrace=False)
    finally:
        shutil.rmtree(checkout)
    tail = "\n".join(run.console.splitlines()[-30:])
    assert run.ok, f"{run.failure or f'job exit {run.rc}'}\n--- guest console ---\n{tail}"
    assert (run.out / "pwd").read_text().strip() == str(checkout)
    assert (run.out / "marker").read_text() == "seen from the guest\n"


@pytest.mark.flaky(reruns=0)
def test_a_silent_kvm_guest_falls_back_to_tcg(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A /dev/kvm that passes the probe but boots nothing leaves qemu silent: the runner must
    notice within its silence limit and boot the same guest under TCG, not wait 900 s.

    The "KVM" qemu here is real but runs a firmware of `hlt`s (it never loads the kernel and
    prints nothing), which is what such a host looks like from outside."""
    has_netem, detail = netem_status()
    if has_netem:
        pytest.skip(f"this host's kernel has sch_netem ({detail}): no VM is booted here")
    hlt = tmp_path / "hlt.bin"
    hlt.write_bytes(b"\xf4" * 65536)
    real_accel_args = netem_vm._accel_args

    def accel_args(accel: str) -> list[str]:
        if accel == "kvm":
            return ["-accel", "tcg", "-cpu", "max", "-bios", str(hlt)]
        return real_accel_args(accel)

    monkeypatch.delenv("EDGELOC_VM_ACCEL", raising=False)
    monkeypatch.setattr(netem_vm, "choose_accel", lambda _qemu: "kvm")
    monkeypatch.setattr(netem_vm, "_accel_args", accel_args)
    monkeypatch.setattr(netem_vm, "KVM_SILENCE_S", 3.0)
    try:
        run = run_in_guest('echo ok > "$VMOUT/ok"', timeout_s=300, workdir=tmp_path / "vm")
    except VmUnavailable as err:
        pytest.fail(f"cannot boot the VM (host kernel: {detail}): {err}", pytrace=False)
    print(*run.notes, sep="\n")
    tail = "\n".join(run.console.splitlines()[-30:])
    assert run.accel == "tcg" and run.ok, f"{run.failure}\n{tail}"
    (note,) = run.notes
    assert note.startswith("the kvm guest printed nothing for 3 s before its init ran")
    assert (run.out / "ok").read_text() == "ok\n"
