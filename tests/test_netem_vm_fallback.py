"""The VM runner gives up on a silent KVM guest within seconds and boots it under TCG.

A /dev/kvm can pass the runner's firmware probe and still not boot the guest kernel: qemu then
sits with an empty console until the time limit (900 s). These tests hand `boot_guest` fake
"qemu" commands (no VM is booted, no root needed): a silent process for KVM and one that
prints the guest init's console lines for TCG.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from tests.vm.netem_vm import BOOTED, EXIT, READY, boot_guest

SILENCE_S = 1.5


def _guest(*lines: str, first_after_s: float = 0.0) -> list[str]:
    """A fake qemu that prints `lines`, the first one after `first_after_s` of silence."""
    echoes = "; ".join(f"echo '{line}'" for line in lines)
    return ["sh", "-c", f"sleep {first_after_s}; {echoes}"]


def _out(tmp_path: Path) -> Path:
    out = tmp_path / "out"
    out.mkdir()
    return out


def test_a_silent_kvm_guest_is_given_up_for_tcg(tmp_path: Path) -> None:
    pid_file = tmp_path / "kvm.pid"
    silent = ["sh", "-c", f"echo $$ > {pid_file}; exec sleep 600"]  # prints nothing
    tcg = _guest(f"{BOOTED} 0.5", f"{READY} 0.9", f"{EXIT} 0")
    out = _out(tmp_path)
    t0 = time.monotonic()
    run = boot_guest(
        lambda a: silent if a == "kvm" else tcg, ["kvm", "tcg"], out, 60, False, SILENCE_S
    )
    took = time.monotonic() - t0
    assert run.accel == "tcg" and run.ok, run
    assert SILENCE_S <= took < SILENCE_S + 5, f"noticed the silence after {took:.1f} s"
    (note,) = run.notes
    assert "kvm guest printed nothing for 1.5 s" in note and "under tcg" in note
    assert note in (tmp_path / "console.log").read_text()
    with pytest.raises(ProcessLookupError):  # the silent qemu was killed, not left behind
        os.kill(int(pid_file.read_text()), 0)


def test_a_kvm_guest_that_talks_is_kept(tmp_path: Path) -> None:
    # slow to reach init but printing (a kernel's boot lines), then quiet while the job runs
    lines = ["[    0.000000] Linux version", f"{BOOTED} 2.0", f"{READY} 2.1", f"{EXIT} 0"]
    slow = [
        "sh",
        "-c",
        f"echo '{lines[0]}'; sleep 0.8; echo '{lines[0]}'; sleep 0.8; echo '{lines[1]}'; "
        f"echo '{lines[2]}'; sleep {SILENCE_S + 1}; echo '{lines[3]}'",
    ]
    run = boot_guest(lambda a: slow, ["kvm", "tcg"], _out(tmp_path), 60, False, SILENCE_S)
    assert run.accel == "kvm" and run.ok and not run.notes, run


def test_a_forced_kvm_that_is_silent_fails_fast(tmp_path: Path) -> None:
    t0 = time.monotonic()
    run = boot_guest(lambda a: ["sleep", "600"], ["kvm"], _out(tmp_path), 60, False, SILENCE_S)
    assert time.monotonic() - t0 < SILENCE_S + 5
    assert run.silent and not run.ok
    assert (
        run.failure
        == "the guest (kvm) printed nothing for 1.5 s before its init ran and was killed"
    )


def test_tcg_gets_no_silence_limit(tmp_path: Path) -> None:
    quiet = _guest(f"{BOOTED} 3.0", f"{EXIT} 0", first_after_s=SILENCE_S + 1)
    run = boot_guest(lambda a: quiet, ["tcg"], _out(tmp_path), 60, False, SILENCE_S)
    assert run.accel == "tcg" and run.ok, run
