"""The packages that export lazily (`testbed.lazyexports`) give the same names as an eager
`__init__` did, whatever was imported first."""

from __future__ import annotations

import subprocess
import sys

import pytest

ORDERS = {
    # the submodule named like its export, imported on its own before the package's name
    "submodule first": "import testbed.topology.build, testbed.topology.plan\n"
    "from testbed.topology import build, plan",
    "package name first": "from testbed.topology import build, plan\n"
    "import testbed.topology.build, testbed.topology.plan",
}


@pytest.mark.parametrize("order", list(ORDERS))
def test_an_export_named_like_its_submodule_is_the_export(order: str) -> None:
    code = ORDERS[order] + (
        "\nimport testbed.topology as t\n"
        "assert callable(build) and callable(plan), (build, plan)\n"
        "assert t.build is build and t.plan is plan\n"
        "assert build.__module__ == 'testbed.topology.build'\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_every_listed_name_resolves_and_an_unknown_one_is_an_attribute_error() -> None:
    import testbed.links
    import testbed.scenario
    import testbed.topology

    for package in (testbed.topology, testbed.links, testbed.scenario):
        for name in package.__all__:
            assert getattr(package, name) is not None, (package.__name__, name)
        assert set(package.__all__) <= set(dir(package))
        with pytest.raises(AttributeError, match="has no attribute 'nothing_here'"):
            package.nothing_here  # noqa: B018
