"""Link self-test: measure what every link of a built network really does and compare it with
its profile.

    with build(scenario, mode="run") as net:
        report = LinkTest(net, quick=True).run()
    print(report.table()); report.ok

- `selftest`: the test itself (`LinkTest`, `link_test` for `testbed link-test`);
- `measure`: the measuring of a tc or relay link between two namespaces;
- `radio`: a radio direction judged against its delay oracle and its BLER;
- `report`: the figures and verdicts (`LinkTestReport`).

`testbed run` runs the quick mode first: every link's delay probes at once (a radio's, tens of
ms apart, set the time), then each link's loss and rates in turn, TCP only where a rate is set
to judge it against (an unshaped link's TCP goodput is the host's; a full test prints it).
A scenario chooses with `report: {link_test: true}` (default), `false`, or a list of links
(`[av1-gnb1]`); a name that is not a link of the topology is a file:line error naming the
likely link. `testbed link-test --link NAME` (repeatable) does the same from the command line.

The UDP rate test sends datagrams that fill the sender's route MTU (IP_MTU): from a UE (MTU
1456, room for GTP-U) 1472-byte datagrams left in two IP fragments and came out under the
rate, which is why the size follows the route.

A radio direction is judged against `netem.nr.oracle.DelayOracle` (the idle UE's one-way delay
in closed form for a packet size; with an SR: the SR wait, the first grant, the report's grants
and every combination of the blocks' retransmissions): probes at phases spread over the TDD
period and far enough apart that each finds the UE idle, their delay CDF beside the oracle's,
Wasserstein-1 and Kolmogorov-Smirnov distances, HARQ retransmission shares against the BLER (4
binomial sigmas over the test's blocks), what a slot carried while the rate test saturated it,
and TCP/UDP rates against the blocks per second that are not resends. The W1 tolerance has two
parts, both printed by `testbed link-test`: the host's (0.3 ms, or 0.25 ms over the 99th
percentile of its timed wake-ups, measured at the start) and the probes' (the 99th percentile
of the distance that as many draws from the oracle itself fall from it: 0.757 ms for the 100
probes of a quick test of OAI's uplink, whose 10% HARQ tail is 5 ms away). Every run's report
shows the same table and a figure of the CDFs.

Full mode on an idle 2-core VM (`testbed link-test scenarios/default.yaml`, three times in a
row): every link and direction within tolerance, the 1 Gbit/s N3 at 965 Mbit/s of TCP each way,
the air uplink at 49.0-49.1 Mbit/s of UDP against 49.0 expected.
"""

from testbed.linktest.measure import (
    CTX,
    IP_PACKET,
    PORT,
    STAMP,
    TCP_PAYLOAD,
    UDP_PAYLOAD,
    Worker,
    goodput_bps,
    in_namespace,
    percentile,
    route_mtu,
    tcp_goodput,
    tcp_receive,
    tcp_send,
    udp_receive,
    udp_send,
    udp_stream,
)
from testbed.linktest.radio import (
    CDF_QUANTILES,
    HARQ_SIGMAS,
    Chance,
    harq_shares,
    oracle_comparison,
    sampling_chance,
    slot_goodput,
)
from testbed.linktest.report import DirectionResult, LinkResult, LinkTestReport, Verdict
from testbed.linktest.selftest import CapacityNote, LinkTest, check_link_names, link_test

__all__ = [
    "CDF_QUANTILES",
    "CTX",
    "HARQ_SIGMAS",
    "IP_PACKET",
    "PORT",
    "STAMP",
    "TCP_PAYLOAD",
    "UDP_PAYLOAD",
    "CapacityNote",
    "Chance",
    "DirectionResult",
    "LinkResult",
    "LinkTest",
    "LinkTestReport",
    "Verdict",
    "Worker",
    "check_link_names",
    "goodput_bps",
    "harq_shares",
    "in_namespace",
    "link_test",
    "oracle_comparison",
    "percentile",
    "route_mtu",
    "sampling_chance",
    "slot_goodput",
    "tcp_goodput",
    "tcp_receive",
    "tcp_send",
    "udp_receive",
    "udp_send",
    "udp_stream",
]
