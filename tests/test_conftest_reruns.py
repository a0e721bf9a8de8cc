"""The suite's own reporting: a test that passed on a rerun still shows why its first try
failed (tests/conftest.py), so a flake in CI leaves its traceback in the log."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_the_failed_try_of_a_rerun_test_is_printed(tmp_path: Path) -> None:
    (tmp_path / "conftest.py").write_text(
        "from tests.conftest import pytest_runtest_logreport, pytest_terminal_summary\n"
    )
    (tmp_path / "test_flake.py").write_text(
        "import pathlib, pytest\n"
        "@pytest.mark.flaky(reruns=1)\n"
        "def test_once():\n"
        f"    flag = pathlib.Path({str(tmp_path / 'tried')!r})\n"
        "    if not flag.exists():\n"
        "        flag.touch()\n"
        "        print('what the test saw')\n"
        "        assert list(range(300)) == list(range(1, 301)), 'the first try fails'\n"
    )
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "-vv", "-p", "no:cacheprovider", "test_flake.py"],
        cwd=tmp_path, capture_output=True, text=True, check=False,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )  # fmt: skip
    print(out.stdout[-2000:])
    assert out.returncode == 0 and "1 passed, 1 rerun" in out.stdout, out.stdout + out.stderr
    summary = out.stdout.split("failed tries of the tests that were rerun")[1]
    summary = summary.split("rerun test summary info")[0]
    assert "test_flake.py::test_once" in summary
    # the assertion itself, not only the end of its 300-line diff; where; what it printed
    assert "AssertionError: the first try fails" in summary
    assert "test_flake.py:8: AssertionError" in summary
    assert "what the test saw" in summary
    assert len(summary.splitlines()) < 60
