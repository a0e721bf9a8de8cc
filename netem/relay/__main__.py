"""The relay process of a userspace link: two TUN ends, two pipelines, one event loop.

Started from the command line (by `netem.relay.client`):

    python -m netem.relay --netns-a NS_A --dev-a tunA --netns-b NS_B --dev-b tunB \\
        --control /run/x.sock [--addr-a 10.0.0.1/30 --addr-b 10.0.0.2/30 --mtu 1500]
        [--uplink '{"delay_s": 0.01}' --downlink '{...}' --seed 1 --die-with-parent]
        [--no-offload]

`--no-offload` reads and writes one MTU-sized packet at a time; `--cell` names the cell whose
NR slots the first link shares. On start it prints one line `{"event": "ready", ...}` to stdout
once both TUNs are up and the control socket listens. SIGTERM or SIGINT -> clean exit (the TUN
devices vanish with it).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys

from netem.nr.policy import SCHEDULERS
from netem.proc import PR_SET_TIMERSLACK, die_with_parent, prctl, renice
from netem.profile import PROFILE_FIELDS, LinkProfile, check_profile
from netem.relay.direction import build_pipeline
from netem.relay.process import Relay
from netem.tun import MAX_MTU, TunConfig, TunError, open_tun_in


def _profile_arg(text: str) -> LinkProfile:
    try:
        data = json.loads(text)
        if not isinstance(data, dict):
            raise ValueError("expected a JSON object of LinkProfile fields")
        unknown = sorted(set(data) - set(PROFILE_FIELDS))
        if unknown:
            raise ValueError(f"unknown field(s) {unknown}; allowed: {', '.join(PROFILE_FIELDS)}")
        profile = LinkProfile.from_dict(data)
        check_profile(profile)
    except (ValueError, TypeError) as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return profile


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m netem.relay", description=__doc__.split("\n")[0])
    p.add_argument("--netns-a", required=True, help="namespace of end A (name or path)")
    p.add_argument("--netns-b", required=True, help="namespace of end B (name or path)")
    p.add_argument("--dev-a", required=True, help="TUN device name of end A")
    p.add_argument("--dev-b", required=True, help="TUN device name of end B")
    p.add_argument("--addr-a", help="address of end A, e.g. 10.0.0.1/30")
    p.add_argument("--addr-b", help="address of end B, e.g. 10.0.0.2/30")
    p.add_argument("--mtu", type=int, default=1500, help=f"MTU of both ends (68..{MAX_MTU})")
    p.add_argument("--name", default="link", help="the first link's name (in control requests)")
    p.add_argument(
        "--cell", help="share NR slots with the links attached to the same cell (a gNB's name)"
    )
    p.add_argument(
        "--scheduler", choices=SCHEDULERS, default="rr", help="how a cell shares its slots"
    )
    p.add_argument("--control", help="path of the control unix socket")
    p.add_argument("--uplink", type=_profile_arg, default=LinkProfile(), help="A->B profile JSON")
    p.add_argument("--downlink", type=_profile_arg, default=LinkProfile(), help="B->A profile")
    p.add_argument("--seed", default="0", help="seed of loss and jitter draws")
    p.add_argument(
        "--nice",
        type=int,
        default=0,
        help="scheduling priority change (negative = sooner; an emulated link should not wait"
        " behind the workload it carries)",
    )
    p.add_argument(
        "--die-with-parent", action="store_true", help="exit when the starting process dies"
    )
    p.add_argument(
        "--no-offload",
        dest="offload",
        action="store_false",
        help="one MTU-sized packet per read and write (no TSO/USO super-packets)",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    prctl(PR_SET_TIMERSLACK, 1)  # 1 ns slack: timers fire as asked
    renice("relay", args.nice)
    if args.die_with_parent and not die_with_parent():
        return 1
    try:
        end_a = TunConfig(args.dev_a, args.mtu, args.addr_a, offload=args.offload)
        end_b = TunConfig(args.dev_b, args.mtu, args.addr_b, offload=args.offload)
    except ValueError as exc:
        print(f"relay: error: {exc}", file=sys.stderr)
        return 2
    fds: list[int] = []
    relay: Relay | None = None
    try:
        fds.append(open_tun_in(args.netns_a, end_a))
        fds.append(open_tun_in(args.netns_b, end_b))
        uplink = build_pipeline(args.uplink, f"{args.seed}:uplink", "uplink")
        downlink = build_pipeline(args.downlink, f"{args.seed}:downlink", "downlink")
        relay = Relay(
            fds[0],
            fds[1],
            uplink,
            downlink,
            args.control,
            mtu=args.mtu,
            offload=args.offload,
            name=args.name,
            cell=args.cell,
            scheduler=args.scheduler,
        )
    except (TunError, OSError, ValueError) as exc:
        print(f"relay: error: {exc}", file=sys.stderr)
        for fd in fds:
            os.close(fd)
        return 1
    signal.signal(signal.SIGTERM, lambda *_: relay.stop())
    signal.signal(signal.SIGINT, lambda *_: relay.stop())
    ready = {"event": "ready", "pid": os.getpid(), "dev_a": args.dev_a, "dev_b": args.dev_b}
    print(json.dumps(ready), flush=True)
    try:
        relay.run()
    finally:
        relay.close()
        for fd in fds:
            os.close(fd)
    return 0


if __name__ == "__main__":
    sys.exit(main())
