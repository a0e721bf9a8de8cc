"""`python -m testbed.cli`: the `testbed` command, for a process that runs it as a module."""

from testbed.cli import main

main()
