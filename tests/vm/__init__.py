"""Run the tc backend's tests inside a throwaway qemu VM with a stock Debian kernel.

Used where the host kernel has no sch_netem (see `tests/vm/netem_vm.py`).
"""
