"""ROS 2 across the emulated 5G path: an action server in the core namespace answers a vehicle's
1 MiB split-inference goal through the gNB router, with the environment `nodes.ros.env` gives.

Also shows why that environment exists: without unicast peers, DDS discovery (multicast,
TTL 1) does not cross the router and the vehicle never finds the server.

The ROS sides run as subprocesses of this file (`python tests/test_ros_discovery_root.py
serve|ask ...`), started inside the namespaces with `Node.popen`; each prints JSON lines.
Figures (discovery time, time to the first answer) are printed with `-s`.
"""

from __future__ import annotations

import array
import json
import os
import signal
import subprocess
import sys
import time
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

PAYLOAD_BYTES = 1 << 20  # a 1 MiB activation
FRAME_ID = 4242
SPLIT_INDEX = 3
ACTION_NAME = "split_inference"


def payload() -> bytes:
    """The deterministic test activation: 0..255 repeated."""
    return bytes(range(256)) * (PAYLOAD_BYTES // 256)


# ---- the ROS sides (run as subprocesses inside the namespaces) ------------------------------


def _emit(**fields: Any) -> None:
    print(json.dumps(fields), flush=True)


def serve() -> int:
    """Core side: answer SplitInference goals until SIGTERM; report each goal's payload."""
    import rclpy
    from edgeloc_interfaces.action import SplitInference
    from rclpy.action import ActionServer
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    stop = False

    def on_term(signum: int, frame: object) -> None:
        nonlocal stop
        stop = True

    # Our own SIGTERM handler, so the loop ends and everything is destroyed before shutdown
    # (Jazzy aborts at exit otherwise); rclpy's would shut the context down under the executor.
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGTERM, on_term)
    node = rclpy.create_node("edge_probe")

    def execute(handle: Any) -> Any:
        received = node.get_clock().now()
        start = time.perf_counter()
        goal = handle.request
        data = bytes(goal.payload)
        _emit(
            event="goal", frame_id=goal.frame_id, bytes=len(data), crc32=zlib.crc32(data),
            split=goal.split_name, codec=goal.codec, shape=list(goal.shape),
        )  # fmt: skip
        handle.succeed()
        result = SplitInference.Result(ok=True, frame_id=goal.frame_id)
        result.split_index = goal.split_index
        result.pose.header.stamp = goal.capture_stamp
        result.pose.header.frame_id = "map"
        result.pose.pose.pose.position.x = float(len(data))
        result.pose.pose.pose.orientation.w = 1.0
        result.edge_compute_s = time.perf_counter() - start
        result.edge_receive_stamp = received.to_msg()
        result.edge_send_stamp = node.get_clock().now().to_msg()
        return result

    server = ActionServer(node, SplitInference, ACTION_NAME, execute)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    _emit(event="ready", pid=os.getpid())
    try:
        while not stop:
            executor.spin_once(timeout_sec=0.1)
    finally:
        server.destroy()
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown()
    return 0


def ask(timeout_s: float) -> int:
    """Vehicle side: find the server, send one 1 MiB goal, print timings and the result.
    Exit 3 when no server was found within `timeout_s`."""
    import rclpy
    from edgeloc_interfaces.action import SplitInference
    from rclpy.action import ActionClient

    t_start = time.monotonic()
    rclpy.init()
    node = rclpy.create_node("vehicle_probe")
    client = ActionClient(node, SplitInference, ACTION_NAME)
    try:
        found = client.wait_for_server(timeout_sec=timeout_s)
        t_found = time.monotonic()
        if not found:
            _emit(event="not-found", waited_s=t_found - t_start)
            return 3
        goal = SplitInference.Goal(vehicle="av1", frame_id=FRAME_ID, split_name="layer3")
        goal.split_index = SPLIT_INDEX
        goal.codec = "raw"
        goal.dtype = "uint8"
        goal.shape = array.array("i", [PAYLOAD_BYTES])
        goal.payload = array.array("B", payload())  # array.array: no per-byte check in rclpy
        goal.capture_stamp = node.get_clock().now().to_msg()
        t_sent = time.monotonic()
        deadline = t_sent + timeout_s
        sent = client.send_goal_async(goal)
        rclpy.spin_until_future_complete(node, sent, timeout_sec=max(0.0, deadline - t_sent))
        handle = sent.result() if sent.done() else None
        if handle is None or not handle.accepted:
            _emit(event="no-goal-response", found_s=t_found - t_start)
            return 4
        answer = handle.get_result_async()
        remaining = max(0.0, deadline - time.monotonic())
        rclpy.spin_until_future_complete(node, answer, timeout_sec=remaining)
        if not answer.done():
            _emit(event="no-result", found_s=t_found - t_start)
            return 5
        t_answer = time.monotonic()
        result = answer.result().result
        _emit(
            event="answer", found_s=t_found - t_start, round_trip_s=t_answer - t_sent,
            first_answer_s=t_answer - t_start, ok=result.ok, frame_id=result.frame_id,
            split_index=result.split_index, x=result.pose.pose.pose.position.x,
            edge_compute_s=result.edge_compute_s,
        )  # fmt: skip
        return 0
    finally:
        client.destroy()
        node.destroy_node()
        rclpy.shutdown()


# ---- the tests -----------------------------------------------------------------------------

pytestmark = [pytest.mark.root, pytest.mark.ros]

THIS = Path(__file__).resolve()


@pytest.fixture
def net(state_dir: Path, interfaces: None) -> Iterator[Any]:
    """av1 -- gnb1 -- core1, torn down after the test whatever happens."""
    from testbed.topology import build, example_scenario

    with build(example_scenario(1, 1), mode="run") as network:
        yield network


def _iface_bytes(node: Any, ifname: str) -> tuple[int, int]:
    """(rx_bytes, tx_bytes) of `ifname` inside `node`'s namespace."""
    (idx,) = node.ipr.link_lookup(ifname=ifname)
    stats = node.ipr.get_links(idx)[0].get_attr("IFLA_STATS64")
    return stats["rx_bytes"], stats["tx_bytes"]


def _start_server(
    net: Any, env: dict[str, str], out: Path, node: str = "core1"
) -> subprocess.Popen[Any]:
    log = out.open("w")
    proc = net[node].popen(
        [sys.executable, str(THIS), "serve"],
        what=f"{node}: ros probe server",
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    log.close()
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        if '"ready"' in out.read_text():
            return proc
        if proc.poll() is not None:
            pytest.fail(f"server exited with {proc.returncode}:\n{out.read_text()[-3000:]}")
        time.sleep(0.05)
    pytest.fail(f"server not ready within 20 s:\n{out.read_text()[-3000:]}")


def _receive_buffers(node: Any, pid: int) -> list[int]:
    """Receive buffer sizes (bytes, as the kernel reports them) of `pid`'s UDP sockets."""
    out = subprocess.run(
        node.nsenter_argv(["ss", "-u", "-a", "-m", "-n", "-p"]),
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    sizes, mine = [], False
    for line in out.splitlines():
        if "users:" in line:
            mine = f"pid={pid}," in line
        elif mine and "skmem:" in line:
            sizes.append(int(line.split("rb", 1)[1].split(",", 1)[0]))
    return sizes


def _stop(proc: subprocess.Popen[Any] | None) -> None:
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)  # nsenter exec()s, so this is the python process
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5)


def _ask(net: Any, env: dict[str, str], timeout_s: float) -> tuple[int, list[dict[str, Any]]]:
    proc = net["av1"].popen(
        [sys.executable, str(THIS), "ask", str(timeout_s)],
        what="av1: ros probe client",
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        out, err = proc.communicate(timeout=timeout_s * 2 + 20)
    finally:
        _stop(proc)
    events = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    if not events:
        pytest.fail(f"client printed nothing (exit {proc.returncode}):\n{err[-3000:]}")
    return proc.returncode, events


@pytest.mark.parametrize("peers", ["both", "vehicle-only"])
def test_goal_of_1mib_crosses_the_gnb(net: Any, tmp_path: Path, peers: str) -> None:
    from nodes.ros.env import SOCKET_BUFFER_BYTES, RosEnv, domain_id_for

    ros = RosEnv(tmp_path / "run", domain_id_for(net.run_id))
    core_ip = net["core1"].address_towards("gnb1")
    vehicle_ip = net["av1"].address_towards("gnb1")
    server_env = ros.environ([vehicle_ip] if peers == "both" else [])
    client_env = ros.environ([core_ip])
    air_before = _iface_bytes(net["gnb1"], "av1")
    backhaul_before = _iface_bytes(net["gnb1"], "core1")
    server = None
    try:
        server = _start_server(net, server_env, tmp_path / "server.log")
        buffers = _receive_buffers(net["core1"], server.pid)
        code, events = _ask(net, client_env, timeout_s=30)
    finally:
        _stop(server)
    seen = [
        json.loads(x) for x in (tmp_path / "server.log").read_text().splitlines() if x[:1] == "{"
    ]
    assert code == 0, events
    answer = events[-1]
    assert answer["event"] == "answer"
    assert answer["ok"] and answer["frame_id"] == FRAME_ID and answer["split_index"] == SPLIT_INDEX
    assert answer["x"] == PAYLOAD_BYTES  # the server echoed the size it received
    # The Fast DDS profile was applied: listening sockets got the 4 MiB buffers (the kernel
    # reports twice what was asked for).
    assert buffers and max(buffers) >= 2 * SOCKET_BUFFER_BYTES, buffers
    goals = [e for e in seen if e["event"] == "goal"]
    assert len(goals) == 1
    assert goals[0]["bytes"] == PAYLOAD_BYTES
    assert goals[0]["crc32"] == zlib.crc32(payload())
    assert goals[0]["shape"] == [PAYLOAD_BYTES] and goals[0]["codec"] == "raw"
    # The bytes went through the router (not shared memory): the gNB received them from the
    # vehicle and sent them on to the core.
    air_rx = _iface_bytes(net["gnb1"], "av1")[0] - air_before[0]
    backhaul_tx = _iface_bytes(net["gnb1"], "core1")[1] - backhaul_before[1]
    assert air_rx >= PAYLOAD_BYTES and backhaul_tx >= PAYLOAD_BYTES, (air_rx, backhaul_tx)
    print(
        f"\n[{peers}] discovery {answer['found_s']:.2f} s, first answer "
        f"{answer['first_answer_s']:.2f} s after client start, goal round trip "
        f"{answer['round_trip_s'] * 1000:.0f} ms, gNB forwarded {air_rx / 1e6:.2f} MB up"
    )


CORE5G = """
version: 1
name: core5g
duration: 20s
topology:
  cells: [{gnb: gnb1, upf: upf1, edge: edge1}]
  vehicles: [{name: av1, gnb: gnb1}]
links:
  backend: userspace
"""


def test_goal_of_1mib_crosses_n3_in_gtp_u(
    state_dir: Path, interfaces: None, tmp_path: Path
) -> None:
    """The same 1 MiB goal from a UE behind a UPF: DDS between the UE's pool address and the
    edge's N6 address, every byte through the gNB's GTP-U tunnel on N3, intact (CRC), with
    no drop at either GTP-U end."""
    from nodes.ros.env import RosEnv, domain_id_for
    from testbed.scenario import load
    from testbed.topology import build

    (tmp_path / "core5g.yaml").write_text(CORE5G)
    with build(load(tmp_path / "core5g.yaml"), mode="run") as net:
        assert net.core is not None
        ros = RosEnv(tmp_path / "run", domain_id_for(net.run_id))
        edge_ip = net.server_address(net.scenario.topology.cells[0])
        ue_ip = net.vehicle_address("av1")
        n3_before = _iface_bytes(net["gnb1"], "upf1")
        server = None
        try:
            server = _start_server(net, ros.environ([ue_ip]), tmp_path / "server.log", "edge1")
            code, events = _ask(net, ros.environ([edge_ip]), timeout_s=30)
        finally:
            _stop(server)
        n3_tx = _iface_bytes(net["gnb1"], "upf1")[1] - n3_before[1]
        ends = net.core.close()
    seen = [
        json.loads(x) for x in (tmp_path / "server.log").read_text().splitlines() if x[:1] == "{"
    ]
    assert code == 0, events
    assert events[-1]["event"] == "answer" and events[-1]["x"] == PAYLOAD_BYTES, events[-1]
    (goal,) = [e for e in seen if e["event"] == "goal"]
    assert (goal["bytes"], goal["crc32"]) == (PAYLOAD_BYTES, zlib.crc32(payload()))
    assert n3_tx >= PAYLOAD_BYTES, n3_tx  # in G-PDUs, over N3
    assert ends["gnb1"]["sent"]["inner_bytes"] >= PAYLOAD_BYTES, ends["gnb1"]
    for key, counters in ends.items():
        assert not any(counters["drops"].values()), (key, counters["drops"])


def test_without_static_peers_discovery_fails_across_the_gnb(net: Any, tmp_path: Path) -> None:
    from nodes.ros.env import RosEnv, domain_id_for

    ros = RosEnv(tmp_path / "run", domain_id_for(net.run_id))
    server_env = ros.environ(static_peers=False)
    client_env = ros.environ(static_peers=False)
    assert "ROS_STATIC_PEERS" not in client_env
    server = None
    try:
        server = _start_server(net, server_env, tmp_path / "server.log")
        code, events = _ask(net, client_env, timeout_s=4)
    finally:
        _stop(server)
    assert code == 3 and events[-1]["event"] == "not-found", events


if __name__ == "__main__":
    verb = sys.argv[1] if len(sys.argv) > 1 else ""
    if verb == "serve":
        sys.exit(serve())
    if verb == "ask" and len(sys.argv) == 3:
        sys.exit(ask(float(sys.argv[2])))
    sys.exit("usage: test_ros_discovery_root.py serve | ask TIMEOUT_S")
