"""The userspace backend's data plane: one relay process per host link (or cell), and the
orchestrator's handle on it.

- `__main__`: `python -m netem.relay ...`, the process; `process`: its event loop (`Relay`);
- `timer`: how long the loop may sleep; `control`: the control protocol on its unix socket;
- `direction`: the standard chain of stages one direction runs; `capture`: its pcapng files;
- `client`: `UserspaceLink`, which starts a relay, talks to it and stops it.

Why a Python relay with TUN offloads, not a compiled data plane: one packet at a time the relay
tops out at tens of thousands of packets per second (`make bench BENCH=relay` prints it), while
with TSO one read carries up to ~44 of TCP's packets; that meets the throughput goals without a
compiled core that every fresh machine would have to build. Plain UDP datagrams (ROS 2's DDS
traffic, a UDP flood) still cross one packet at a time; `testbed.capacity` warns where a
scenario's rate depends on that.

Measured (`make bench BENCH=relay`: a plain veth pair, the relay with --no-offload, the relay
with offloads, in one run; 2-core VM, every goal met):
  TCP, 5 ms delay each way, MTU 1500: veth 16,910, no-offload 910, offload 12,232 Mbit/s
    (goal >= 2 Gbit/s)
  relay CPU per 100 Mbit/s of shaped TCP: 54% -> 14% of a core (goal <= 20%; this figure moves
    with what else the cores run: 23% and 28-32% on other days)
  median delay error at 1000 packets/s, 5/20/50 ms: -0.004/-0.004/-0.012 ms ->
    +0.053/+0.016/+0.015 ms (goal <= 0.1 ms)
  TCP at a 1 Gbit/s rate: -26.87% -> -0.12% (goal +-2%)
  loss 5% at 1 Gbit/s (UDP GSO): 5.89% -> 4.99% (goal +-0.5 pp)
  1472-byte datagrams/s, one per packet: veth 127,531, 116,933 -> 100,548 (information)
`make bench BENCH=nr`: one NR cell carried 1058 Mbit/s with 1 UE and 648 Mbit/s with 8, against
658-763 and 268-433 Mbit/s with a write per packet.
"""
