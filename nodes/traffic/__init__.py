"""Cross-traffic generators: flows between two nodes of a scenario that load its links the way
other users of a cell would, and measure what the network did to them.

A flow is a sender process and a receiver process, each started inside a node's network
namespace as `python -m nodes.traffic.gen send|recv ...` (see `gen` for the command line, the
stats JSON and the sample lines). Its kinds:

- bulk TCP (`tcp`): as fast as the socket takes data, or capped at a rate;
- constant bit rate UDP (`udp`): one datagram of a given size every size*8/rate seconds;
- on/off UDP (`onoff`, video-like): CBR during `on` seconds, silent for `off`, repeating.

The nouns and their jobs:

- `flows`: the logic, without sockets, driven by the caller's clock so tests can fake it:
  the datagram header, the schedules (`Cbr`, `OnOff`), the sender's deadlines (`Pacer`),
  the sample grid (`Ticker`), loss from sequence numbers (`SeqTracker`), delay quantiles
  (`Histogram`), a receiver's and a sender's accounts (`RecvAccount`, `SendAccount`), and
  the kernel's `struct tcp_info` (`parse_tcp_info`);
- `gen`: the processes: sockets, the send and receive loops, signals, the files written.

Pure Python with no ROS import: the orchestrator starts these processes and records what
they write.
"""
