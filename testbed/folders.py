"""Folders a verb writes its results into, checked before the work that fills them.

A run builds a network and plays a timeline for minutes, and a sweep runs many; a results
folder it cannot write must stop it at the start with the option's name and the reason, not
with a traceback once the work is done. The check creates nothing: a verb that then fails on
other grounds (no root, a bad scenario) leaves no empty folder behind.
"""

from __future__ import annotations

import os
from pathlib import Path

from testbed.errors import BadInput


def check_writable_folder(path: Path, what: str) -> Path:
    """`path` if this process can write results there: an existing folder it may write in,
    or one it may create (the nearest existing folder above it is writable). Raises
    `BadInput` naming `what` (an option such as `--runs-dir`, or "run folder") and why not."""
    if path.exists() and not path.is_dir():
        raise BadInput(f"{what} {path}: expected a folder, found a file")
    probe = path
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    where = "" if probe == path else f" (it would be created in {probe})"
    if not probe.is_dir():
        raise BadInput(f"{what} {path}: {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        owner = " (it belongs to root: run it with sudo)" if _root_owned(probe) else ""
        raise BadInput(f"{what} {path}: this user cannot write there{where}{owner}")
    return path


def make_folder(path: Path, what: str) -> Path:
    """Create `path` (and its parents); what the kernel refuses becomes `BadInput` with
    `what` and the reason (a read-only or virtual file system that `check_writable_folder`
    cannot tell from the permission bits)."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise BadInput(f"{what} {path}: cannot create it: {err.strerror or err}") from None
    return path


def _root_owned(path: Path) -> bool:
    try:
        return os.geteuid() != 0 and path.stat().st_uid == 0
    except OSError:
        return False
