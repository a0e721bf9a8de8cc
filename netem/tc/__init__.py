"""The `tc` backend: kernel qdiscs where the kernel has `sch_netem`.

- `plan`: every change as a list of qdisc/class/filter operations (also `tc` command lines);
- `netlink`: the same operations as netlink messages, sent and read back with pyroute2;
- `link`: a shaped interface, an IFB ingress shaper and one link's backend;
- `shaping`: Wondershaper-style caps on a node's interfaces; `sniff`: the capture process.

HTB classes keep 4 ms of burst (what `tc` computes on a HZ=250 kernel) rather than tc's
one-mtu default on high-resolution-timer kernels: with one mtu every late qdisc watchdog is lost
sending time, and on a VM a class then delivered well under its rate.

Where the host kernel lacks sch_netem, `make test-netem` runs this backend's tests in a
throwaway VM (tests/vm/netem_vm.py). Packet captures of a tc link come from an AF_PACKET
listener on both veth ends (`sniff`), since no relay sees its packets; there the link's drops
are netem's to count, so a capture's statistics say none were seen (`dropped` null in run.json).
"""
