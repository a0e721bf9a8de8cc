"""GTP-U on N3 in user space: `wire`, the datagrams (pure bytes), and `endpoint`, the gNB's and
the UPF's processes that move them (`python -m netem.gtpu.endpoint`).

The endpoints' data path: runs of equal-sized datagrams leave in one sendmsg (UDP GSO) and
arrive coalesced (UDP GRO). Each end reads its TUN one packet at a time (the kernel segments TCP
faster than Python could) and writes what it unwraps coalesced: a run of one TCP flow's
in-sequence segments goes into the TUN as one TSO super-packet behind a virtio-net header
(software GRO; split again it gives back the very packets), so the stack behind handles one
packet where it would have handled ~20-40. A capture writes a super-packet segment by segment,
as a wire carries it, so every frame on N3 is one G-PDU; tshark live on a userspace N3 device
instead shows fewer, larger frames (it dissects the first G-PDU of each).

`sudo .venv/bin/python tests/bench/bench_gtp.py` (part of `make bench`) measures the tunnel
against plain forwarding on veth pairs, with the ends writing one packet at a time
(EndpointConfig(offload=False)) and coalesced: on a 2-vCPU VM, two runs, TCP 2.38 and 2.58
Gbit/s through the tunnel (goal >= 1 Gbit/s; one packet per write 1.67 and 1.71; plain veth
44.5 and 49.7), 0.089 and 0.073 ms added each way for packets 2 ms apart (goal <= 0.1 ms; back
to back 0.082 and 0.056). Other days gave 0.104 and 0.128 ms: what is left is two process
wake-ups per way, and how fast a VM's idle vCPUs wake varies; the testbed does not change a
host's idle states to shorten them.

tests/test_gtp_root.py checks with tshark on the gNB's N3 device that every UDP/2152 datagram
dissects as GTP-U with the session's TEID per direction, PDU type and QFI, that no outer packet
is a fragment, that the inner source is in the UE pool, that the UE's MTU is 1456 with its
default route through the PDU device, and that 1 MiB of TCP crosses intact;
tests/test_ros_discovery_root.py sends EdgeLoc's 1 MiB activation goal over real DDS from a UE
behind a UPF to its edge (CRC checked, no drop at either end).
"""
