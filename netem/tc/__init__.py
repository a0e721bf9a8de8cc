"""The `tc` backend: kernel qdiscs where the kernel has `sch_netem`.

- `plan`: every change as a list of qdisc/class/filter operations (also `tc` command lines);
- `netlink`: the same operations as netlink messages, sent and read back with pyroute2;
- `link`: a shaped interface, an IFB ingress shaper and one link's backend;
- `shaping`: Wondershaper-style caps on a node's interfaces; `sniff`: the capture process.
"""
