"""A vehicle's nodes learn their serving cell from their own default route
(`nodes.ros.serving`), and the supervisor wires `edge: follow` (`testbed.supervisor`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from nodes.ros.serving import ServingEdge, default_interface, parse_edges

# /proc/net/route of a vehicle served by gnb2: its default route, then its links' subnets.
TABLE = """\
Iface\tDestination\tGateway \tFlags\tRefCnt\tUse\tMetric\tMask\t\tMTU\tWindow\tIRTT
gnb1\t0C00C80A\t00000000\t0001\t0\t0\t0\tFCFFFFFF\t0\t0\t0
gnb2\t00000000\t1200C80A\t0003\t0\t0\t0\t00000000\t0\t0\t0
gnb2\t1000C80A\t00000000\t0001\t0\t0\t0\tFCFFFFFF\t0\t0\t0
"""


def test_the_default_route_s_interface_is_the_serving_cell() -> None:
    assert default_interface(TABLE) == "gnb2"
    assert default_interface(TABLE.splitlines()[0]) is None


def test_the_serving_cell_s_edge_is_asked(tmp_path: Path) -> None:
    table = tmp_path / "route"
    table.write_text(TABLE)
    edges = {"gnb1": "edge1", "gnb2": "edge2"}
    assert ServingEdge("edge1", edges, table).now() == "edge2"
    table.write_text(TABLE.replace("gnb2\t00000000", "gnb1\t00000000"))
    assert ServingEdge("edge1", edges, table).now() == "edge1"
    assert ServingEdge("edge1", {}, table).now() == "edge1"  # no handovers: always --edge
    assert ServingEdge("edge1", edges, tmp_path / "gone").now() == "edge1"


def test_edges_parse_and_bad_ones_say_why() -> None:
    assert parse_edges("gnb1=edge1, gnb2=edge2") == {"gnb1": "edge1", "gnb2": "edge2"}
    assert parse_edges("") == {}
    with pytest.raises(ValueError, match="gnb=edge pairs"):
        parse_edges("gnb1")


def test_follow_wires_each_vehicle_to_every_edge_it_may_ask() -> None:
    from ipaddress import IPv4Network

    from testbed.scenario import loads
    from testbed.supervisor import asking, ros_peers
    from testbed.topology import plan

    text = """\
name: follow
duration: 20s
topology:
  cells:
    - {{gnb: gnb1, upf: upf1, edge: edge1, site: {{x: 0, y: 30}}}}
    - {{gnb: gnb2, upf: upf1, edge: edge2, site: {{x: 400, y: 30}}}}
  vehicles: [{{name: av1, gnb: gnb1}}]
links:
  air: {{radio: oai-tdd-30k}}
channel:
  model: uma
  handover: {{edge: {edge}}}
"""
    follow = loads(text.format(edge="follow"))
    stay = loads(text.format(edge="stay"))
    av1 = follow.topology.vehicles[0]
    assert [follow.edge_via(av1, g) for g in ("gnb1", "gnb2")] == ["edge1", "edge2"]
    assert [stay.edge_via(av1, g) for g in ("gnb1", "gnb2")] == ["edge1", "edge1"]
    assert [v.name for v in asking(follow, "edge2")] == ["av1"]
    assert asking(stay, "edge2") == []
    net = plan(follow, "abc123", IPv4Network("10.99.0.0/24"))
    edge_addrs = {str(net.server_address(c)) for c in follow.topology.cells}
    assert edge_addrs <= set(ros_peers(net, "av1"))
    stay_net = plan(stay, "abc124", IPv4Network("10.99.0.0/24"))
    first = str(stay_net.server_address(stay.topology.cells[0]))
    assert ros_peers(stay_net, "av1") == [first, "127.0.0.1"]
    from testbed.replay.path import _PathPlan

    # The replay's path after a handover: the target's N3, then the edge asked.
    assert [w.name for w in _PathPlan(follow, None).paths["gnb2"]] == ["gnb2-upf1", "upf1-edge2"]
    assert [w.name for w in _PathPlan(stay, None).paths["gnb2"]] == ["gnb2-upf1", "upf1-edge1"]
