"""GTP-U on N3 in user space: `wire`, the datagrams (pure bytes), and `endpoint`, the gNB's and
the UPF's processes that move them (`python -m netem.gtpu.endpoint`)."""
