"""The userspace backend's data plane: one relay process per host link (or cell), and the
orchestrator's handle on it.

- `__main__`: `python -m netem.relay ...`, the process; `process`: its event loop (`Relay`);
- `timer`: how long the loop may sleep; `control`: the control protocol on its unix socket;
- `direction`: the standard chain of stages one direction runs; `capture`: its pcapng files;
- `client`: `UserspaceLink`, which starts a relay, talks to it and stops it.
"""
