"""Link self-test: measure what every link of a built network really does and compare it with
its profile.

    with build(scenario, mode="run") as net:
        report = LinkTest(net, quick=True).run()
    print(report.table()); report.ok

- `selftest`: the test itself (`LinkTest`, `link_test` for `testbed link-test`);
- `measure`: the measuring of a tc or relay link between two namespaces;
- `radio`: a radio direction judged against its delay oracle and its BLER;
- `report`: the figures and verdicts (`LinkTestReport`).
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
