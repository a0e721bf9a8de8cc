"""Scenario files -> `Scenario`: parse YAML keeping positions, check it, convert to SI units.

Three passes, each reporting `Issue`s with file:line:column and the field path:
1. YAML syntax (PyYAML's composer keeps every node's position; nothing is constructed that
   is not a plain scalar, so loading never runs anything);
2. the declarations of `schema_v1.py`, made of the kinds of `kinds.py` (types, units, ranges,
   allowed values, unknown and duplicate keys);
3. the rules that join fields (`_Builder`): names defined once and referred to correctly,
   times inside the run, trace files that exist and parse, paths relative to the file.
All issues of a file are collected; a rule that depends on a broken part is skipped rather
than piling up errors that only repeat the first one.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml
from yaml.nodes import Node

from netem.nr.radio import RADIO_PROFILES, Radio
from netem.nr.rrc import RrcSettings
from netem.profile import GilbertElliott, LinkProfile
from netem.traces import TraceError, TraceProblem, default_format
from testbed import units
from testbed.scenario import channel, model, radios, schema_v1
from testbed.scenario.issues import ROOT_PATH, Issue, ScenarioError, did_you_mean
from testbed.scenario.kinds import Context, Invalid, Items, Section, item
from testbed.scenario.programs import Programs

__all__ = ["load", "loads", "profile_changes"]

#: Names of this scenario (nodes, links, splits) are short words, so a misspelt one is matched
#: more loosely than a key of the schema (`kinds.SPELLING_CUTOFF`).
NAME_CUTOFF = 0.5
DIRS = ("uplink", "downlink")


def load(path: str | Path) -> model.Scenario:
    """Read and check a scenario file; raise `ScenarioError` listing everything wrong."""
    path = Path(path)
    shown = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise _file_error(shown, "an existing scenario file", "no such file") from None
    except IsADirectoryError:
        raise _file_error(shown, "a scenario file", "a directory") from None
    except UnicodeDecodeError as err:
        raise ScenarioError([_undecodable(shown, err)]) from None
    except OSError as err:
        raise _file_error(shown, "a readable scenario file", err.strerror or str(err)) from None
    return _load(text, shown, path.parent, path.parent, path)


def loads(
    text: str, source: str = "<string>", base_dir: str | Path | None = None
) -> model.Scenario:
    """Check scenario YAML given as text. `source` names it in messages; relative paths in it
    (traces, dataset, weights) are resolved against `base_dir` (default: the current folder)."""
    base = Path(base_dir) if base_dir is not None else Path.cwd()
    display = Path(base_dir) if base_dir is not None else Path()
    return _load(text, source, base, display, None)


def _file_error(file: str, expected: str, found: str) -> ScenarioError:
    return ScenarioError([Issue(file, None, None, "", expected, found)])


def _undecodable(file: str, err: UnicodeDecodeError) -> Issue:
    """Where the first byte that is not UTF-8 is: line and column (in characters, as PyYAML
    counts them for every other issue) and its byte offset, which an editor can jump to."""
    data = bytes(err.object)
    line_start = data.rfind(b"\n", 0, err.start) + 1
    line = data.count(b"\n", 0, err.start) + 1
    # the line's bytes before the bad one are valid UTF-8: the error is at the first bad byte
    column = len(data[line_start : err.start].decode("utf-8")) + 1
    return Issue(
        file,
        line,
        column,
        "",
        "a UTF-8 text file",
        f"byte 0x{data[err.start]:02x} at byte offset {err.start}, which is not UTF-8 "
        f"({err.reason})",
    )


def _load(
    text: str, source: str, base_dir: Path, display_dir: Path, path: Path | None
) -> model.Scenario:
    ctx = Context(source)
    root = _compose(text, ctx)
    section: Section | None = None
    if root is not None:
        try:
            section = schema_v1.SCENARIO.check(root, ctx, "")
        except Invalid as err:
            ctx.add(root, ROOT_PATH, err.expected, err.found, err.hint)
    elif not ctx.issues:
        ctx.issues.append(
            Issue(source, 1, 1, ROOT_PATH, schema_v1.SCENARIO.expected, "an empty document")
        )
    scenario = None
    if section is not None:
        scenario = _Builder(ctx, section, base_dir, display_dir, path).build()
    if ctx.issues or scenario is None:
        issues = sorted(
            ctx.issues, key=lambda i: (i.file != source, i.file, i.line or 0, i.column or 0)
        )
        raise ScenarioError(issues)
    return scenario


def _compose(text: str, ctx: Context) -> Node | None:
    """The YAML node tree, or None (with an issue) when the text is not YAML."""
    try:
        return yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        problem = err.problem or "a syntax error"
        context = (
            f"{err.context} (line {err.context_mark.line + 1})"
            if err.context and err.context_mark
            else err.context
        )
        ctx.issues.append(
            Issue(
                ctx.file,
                mark.line + 1 if mark else None,
                mark.column + 1 if mark else None,
                "",
                "valid YAML",
                f"a syntax error: {problem}",
                context,
            )
        )
    except yaml.reader.ReaderError as err:
        before = text[: err.position]
        line = before.count("\n") + 1
        column = err.position - (before.rfind("\n") + 1) + 1
        ctx.issues.append(
            Issue(ctx.file, line, column, "", "printable text", f"character {err.character!r}")
        )
    except yaml.YAMLError as err:  # pragma: no cover - every PyYAML error above carries a mark
        ctx.issues.append(Issue(ctx.file, None, None, "", "valid YAML", str(err)))
    return None


# ---- profiles -------------------------------------------------------------------------------


def profile_changes(
    section: Section,
    ctx: Context | None = None,
    radio_base: Radio | None = None,
    with_radio: bool = True,
    check_radio: bool = True,
) -> dict[str, object]:
    """`LinkProfile` fields (SI) set by the profile keys written in `section`.

    Keys that set one of two alternatives also clear the other (a loss percentage removes a
    Gilbert-Elliott model, a packet queue limit removes a time limit), so merging and `set`
    events never leave both in place. A radio whose fields do not fit together (a pattern
    whose period TS 38.331 does not allow, say) is reported to `ctx` at its line. A radio
    mapping without a `profile` changes `radio_base` (`testbed.scenario.radios`); with
    `with_radio` off the radio is left to the caller.
    """
    v = section.values
    changes: dict[str, object] = {}
    if "radio" in v and with_radio:
        radio = _radio(v["radio"], section, ctx, radio_base, check_radio)
        if radio is not False:
            changes["radio"] = radio
    if "rate" in v:
        changes["rate_bps"] = v["rate"]
    if "delay" in v:
        changes["delay_s"] = v["delay"]
    if "jitter" in v:
        changes["jitter_s"] = v["jitter"]
    if "jitter_distribution" in v:
        changes["jitter_distribution"] = v["jitter_distribution"]
    if "loss" in v:
        loss = v["loss"]
        if isinstance(loss, Section):
            if loss.clean:  # a broken model was reported; there is nothing to build
                ge: GilbertElliott = loss.obj.build(loss)
                changes.update(loss=0.0, gilbert_elliott=ge)
        else:
            changes.update(loss=loss, gilbert_elliott=None)
    if "queue" in v:
        queue = v["queue"]
        if isinstance(queue, int):
            changes.update(queue_packets=queue, queue_time_s=None)
        else:
            changes.update(queue_packets=None, queue_time_s=queue)
    if "reorder" in v:
        changes["reorder"] = v["reorder"]
    return changes


def _radio(
    value: object,
    section: Section,
    ctx: Context | None,
    base: Radio | None = None,
    check: bool = True,
) -> Radio | bool | None:
    """The `Radio` a `radio` key names or describes over `base` (False: reported, none
    built). Without `check` its fields are not checked together (a later layer may still
    change them: the caller checks what they add up to)."""
    if value is None:
        return None
    if isinstance(value, str):
        return RADIO_PROFILES[value]
    assert isinstance(value, Section)
    if not value.clean:
        return False
    radio = radios.changed(value.values, base)
    why = radios.problem(radio) if check else None
    if why is None:
        return radio
    if ctx is not None:
        _misfit(ctx, section, why)
    return False


def _misfit(ctx: Context, section: Section, why: str) -> None:
    ctx.add(
        section.at("radio"),
        section.path_of("radio"),
        "a radio whose fields fit together (TS 38.211/38.213/38.331)",
        why,
    )


def _trace_problems(text: str, fmt: str) -> list[TraceProblem]:
    """The wrong lines of a trace, as the link emulator's own parser (`netem.traces`, the only
    trace parser) finds them, so a trace that validates is one a run accepts."""
    from netem import traces as emulator_traces

    try:
        if fmt == "csv":
            emulator_traces.parse_csv(text, source="")
        else:
            emulator_traces.parse_mahimahi(text, source="")
    except TraceError as err:
        return list(err.problems)
    except ValueError as err:  # a message without structured problems: `line N: text`
        m = re.match(r"^ ?line (\d+): (.*)$", str(err))
        if m:
            return [TraceProblem(int(m[1]), "a line the link emulator accepts", m[2], m[2])]
        text = str(err).lstrip(": ")
        return [TraceProblem(1, "a trace the link emulator accepts", text, text)]
    return []


def _listing(names: list[str], limit: int = 8) -> str:
    shown = names[:limit] + (["..."] if len(names) > limit else [])
    return ", ".join(shown) if shown else "none"


ROLE_TEXT = {"core": "a core", "upf": "a UPF", "edge": "an edge server", "vehicle": "a vehicle"}
#: The link kinds with defaults in `links` (`model.LinkKind`).
LINK_KINDS = ("air", "backhaul", "n3", "n6")


def _rrc(value: Section | None) -> RrcSettings | None:
    """A `rrc` mapping built (null: always connected); `idle_after: null` is never IDLE."""
    if value is None:
        return None
    built: RrcSettings = schema_v1.RRC.build(value)
    if built.idle_after_s is None:
        built = dataclasses.replace(built, idle_after_s=math.inf)
    return built


def _edge_name(cell: Section) -> str | None:
    """A cell's edge server, written as a name or as {name, placement}."""
    edge = cell.get("edge")
    return edge.get("name") if isinstance(edge, Section) else edge


# ---- rules that join fields -----------------------------------------------------------------


class _Builder:
    """Checks the rules between fields and builds the `Scenario` when nothing is wrong."""

    def __init__(
        self, ctx: Context, root: Section, base_dir: Path, display_dir: Path, path: Path | None
    ) -> None:
        self.ctx, self.root = ctx, root
        self.base_dir, self.display_dir, self.path = base_dir, display_dir, path
        self.duration: float | None = root.get("duration")
        self.roles: dict[str, str] = {}  # node name -> vehicle | gnb | core
        self.topology_ok = False  # every node known: references to unknown names are errors
        self.link_kinds: dict[str, str] = {}  # link name -> air | backhaul
        self.link_specs: dict[str, model.LinkSpec] = {}  # the links, once they checked out
        # node -> (its host, the field path and YAML node where it is listed): `topology.hosts`
        self.placed: dict[str, tuple[str, str, Node]] = {}

    def build(self) -> model.Scenario | None:
        topology = self._topology()
        links = self._links()
        if topology is not None and links is not None:
            self._check_links_across_hosts(topology, links)
        timeline = self._timeline()
        workload = self._workload()
        channel.check_sites(self.ctx, self.root)
        channel.check_timeline(self.ctx, self.root, self.link_kinds)
        channel.check_handover(self.ctx, self.root)
        channel_spec = channel.spec(self.ctx, self.root, self.base_dir, self.display_dir)
        record, report = self.root.get("record"), self.root.get("report")
        if record is not None:
            self._check_links_named(record, "pcap")
        if report is not None:
            self._check_links_named(report, "link_test")
        programs = Programs(self.ctx, self.base_dir, self.duration, self._check_node)
        apps = programs.apps(self.root.get("apps"))
        traffic = programs.traffic(self.root.get("traffic"))
        topics = programs.topics(record.get("topics") if record is not None else None)
        if self.ctx.issues or topology is None or links is None:
            return None
        built_record = record.obj.build(record) if record else model.Record()
        scenario = model.Scenario(
            name=self.root["name"],
            seed=self.root["seed"],
            duration_s=self.root["duration"],
            topology=topology,
            links=links,
            timeline=tuple(sorted(timeline, key=lambda e: e.at_s)),
            workload=workload,
            record=dataclasses.replace(built_record, topics=topics),
            report=report.obj.build(report) if report else model.Report(),
            apps=apps,
            traffic=traffic,
            channel=channel_spec,
            source=self.path,
            version=self.root["version"],
        )
        return channel.apply(self.ctx, self.root, scenario)

    # -- topology --

    def _topology(self) -> model.Topology | None:
        topo: Section | None = self.root.get("topology")
        if topo is None:
            return None
        cells: Items | None = topo.get("cells")
        vehicles: Items | None = topo.get("vehicles")
        first: dict[str, tuple[str, Node]] = {}  # name -> (path, node) where first defined

        def define(section: Section, key: str, role: str, name: str | None = None) -> None:
            name = section.get(key) if name is None else name
            if name is None:
                return
            if name in first and role in ("upf", "edge") and self.roles.get(name) == role:
                return  # cells may share one UPF and one edge server
            if name in first:
                where, node = first[name]
                self.ctx.add(
                    section.at(key),
                    section.path_of(key),
                    "a name not used by another node (names are unique across vehicles, "
                    "gNBs and cores)",
                    f"{name!r}, already used at {where} (line {node.start_mark.line + 1})",
                    "names become namespace and interface names, so each must be unique",
                )
                return
            first[name] = (section.path_of(key), section.at(key))
            self.roles[name] = role

        for _, cell, _ in cells.good() if cells else ():
            define(cell, "gnb", "gnb")
            define(cell, "core", "core")
            define(cell, "upf", "upf")
            define(cell, "edge", "edge", _edge_name(cell))
            self._check_cell_form(cell)
        self._check_shared_edges(cells)
        for _, vehicle, _ in vehicles.good() if vehicles else ():
            define(vehicle, "name", "vehicle")
        gnbs = [n for n, r in self.roles.items() if r == "gnb"]
        if cells is not None:
            for _, vehicle, _ in vehicles.good() if vehicles else ():
                gnb = vehicle.get("gnb")
                if gnb is None or gnb in gnbs:
                    continue
                role = self.roles.get(gnb)
                hint = (
                    f"{gnb!r} is {ROLE_TEXT.get(role, role)}, not a gNB"
                    if role
                    else did_you_mean(gnb, gnbs, NAME_CUTOFF)
                )
                self.ctx.add(
                    vehicle.at("gnb"),
                    vehicle.path_of("gnb"),
                    f"the name of a gNB defined in topology.cells ({_listing(gnbs)})",
                    repr(gnb),
                    hint,
                )
        self.topology_ok = topo.clean and not self.ctx.issues
        # Link names come from the parts that checked out, so later references can be checked.
        handover = channel.wants_handover(self.root)
        for _, vehicle, _ in vehicles.good() if vehicles else ():
            if vehicle.get("name") and vehicle.get("gnb") in gnbs:
                self.link_kinds[f"{vehicle['name']}-{vehicle['gnb']}"] = "air"
        # With handovers a vehicle has a link to every gNB (`model.Scenario.gnbs_of`).
        for _, vehicle, _ in vehicles.good() if vehicles and handover else ():
            if vehicle.get("name") and vehicle.get("gnb") in gnbs:
                for gnb in gnbs:
                    self.link_kinds.setdefault(f"{vehicle['name']}-{gnb}", "air")
        for _, cell, _ in cells.good() if cells else ():
            gnb, core, upf, edge = (
                cell.get("gnb"),
                cell.get("core"),
                cell.get("upf"),
                _edge_name(cell),
            )
            if gnb and core:
                self.link_kinds[f"{gnb}-{core}"] = "backhaul"
            elif gnb and upf and edge:
                self.link_kinds[f"{gnb}-{upf}"] = "n3"
                lower = gnb if channel.placement(cell) == "cell" else upf
                self.link_kinds[f"{lower}-{edge}"] = "n6"
        pool = topo.get("address_pool")
        ue_pool = topo.get("ue_pool") or model.DEFAULT_UE_POOL
        if pool is not None and ue_pool.overlaps(pool):
            self.ctx.add(
                topo.at("ue_pool") if topo.written("ue_pool") else topo.at("address_pool"),
                topo.path_of("ue_pool")
                if topo.written("ue_pool")
                else topo.path_of("address_pool"),
                f"a UE pool apart from the link addresses (address_pool {pool})",
                f"'{ue_pool}'",
                "a packet to a vehicle would match a link's route; pick another private range",
            )
        if pool is not None and cells is not None and vehicles is not None:
            needed = len(self.link_kinds)
            room = 2 ** max(0, 30 - pool.prefixlen) if pool.prefixlen <= 30 else 0
            if room < needed:
                prefix = 30 - max(0, (needed - 1).bit_length())
                self.ctx.add(
                    topo.at("address_pool"),
                    topo.path_of("address_pool"),
                    f"a network with room for one /30 per link ({needed} links need a "
                    f"/{prefix} or larger)",
                    f"'{pool}' (room for {room})",
                )
        qos = self._qos(topo.get("qos"))
        hosts = self._hosts(topo)
        if not self.topology_ok or qos is None or hosts is None:
            return None
        assert cells is not None and vehicles is not None
        return model.Topology(
            vehicles=tuple(schema_v1.VEHICLE.build(v) for _, v, _ in vehicles.good()),
            cells=tuple(self._cell(c) for _, c, _ in cells.good()),
            address_pool=pool,
            ue_pool=ue_pool,
            ue_mtu=topo.get("ue_mtu", model.MAX_UE_MTU),
            qos=qos,
            hosts=hosts,
        )

    def _hosts(self, topo: Section) -> tuple[model.Host, ...] | None:
        """`topology.hosts`: each host's underlay address and nodes; None when one is wrong
        (reported). A node is on one host at most; hosts have addresses of their own; and the
        link addresses must be the same on every host, so the pool is written down."""
        hosts: dict[str, Any] | None = topo.get("hosts")
        if not hosts:
            return ()  # every node on this host (a broken `hosts` is reported already)
        ok = True
        built: list[model.Host] = []
        owner: dict[ipaddress.IPv4Address, str] = {}  # address -> the host that has it
        for name, host in hosts.items():
            if not isinstance(host, Section) or not host.clean:
                ok = False
                continue
            address = self._underlay_address(host, owner.get)
            if address is None:
                ok = False
            else:
                owner.setdefault(address, name)
            nodes: Items | None = host.get("nodes")
            for i, node, at in nodes.good() if nodes else ():
                path = item(nodes.path, i) if nodes else ""
                if self.topology_ok and node not in self.roles:
                    ok = False
                    self.ctx.add(
                        at,
                        path,
                        f"the name of a node of this topology ({_listing(list(self.roles))})",
                        repr(node),
                        did_you_mean(node, list(self.roles), NAME_CUTOFF),
                    )
                elif node in self.placed:
                    ok = False
                    other, where, first = self.placed[node]
                    self.ctx.add(
                        at,
                        path,
                        "each node on one host",
                        f"{node!r} again (already on host {other!r} at {where}, line "
                        f"{first.start_mark.line + 1})",
                        "a node is one namespace on one machine; list it under one host",
                    )
                else:
                    self.placed[node] = (name, path, at)
            if address is not None:
                listed = tuple(node for _, node, _ in nodes.good()) if nodes else ()
                built.append(model.Host(name, address, listed))
        if len(hosts) > 1 and topo.get("address_pool") is None:
            ok = False
            self.ctx.add(
                self.ctx.key_of.get(id(topo.at("hosts")), topo.at("hosts")),
                topo.path_of("address_pool"),
                "topology.address_pool with topology.hosts",
                f"{len(hosts)} hosts and no address_pool",
                "every host must give the links the same addresses, so write the pool "
                "down (a private network none of the hosts uses, e.g. 10.77.0.0/16)",
            )
        return tuple(built) if ok else None

    def _underlay_address(
        self, host: Section, taken: Callable[[ipaddress.IPv4Address], str | None]
    ) -> ipaddress.IPv4Address | None:
        """A host's `address` as an IPv4 address another host can send VXLAN to; None when
        it is not one (reported). `taken(address)` names a host that has it already."""
        text = host["address"]
        expected = "a unicast IPv4 address of this host that the other hosts reach"
        try:
            address = ipaddress.IPv4Address(text)
        except ValueError as err:
            self.ctx.add(host.at("address"), host.path_of("address"), expected, repr(text),
                         str(err))  # fmt: skip
            return None
        why = (
            "it is a loopback address, which no other host reaches"
            if address.is_loopback
            else "VXLAN here is unicast from host to host"
            if address.is_multicast
            else "it is no host's address"
            if address.is_unspecified or address.is_reserved
            else None
        )
        other = taken(address)
        if why is None and other is not None:
            expected = "an address of its own"
            why = f"host {other} has it too; each host's tunnels end at its own address"
        if why is not None:
            self.ctx.add(host.at("address"), host.path_of("address"), expected, repr(text), why)
            return None
        return address

    def _check_links_across_hosts(self, topology: model.Topology, links: model.Links) -> None:
        """An air link whose profiles have an NR radio stays on one host: the air links of a
        gNB share its cell's slots in one relay, which cannot reach across a tunnel."""
        for spec in links.links:
            if spec.uplink.radio is None and spec.downlink.radio is None:
                continue
            lower, upper = topology.host_of(spec.lower), topology.host_of(spec.upper)
            if lower == upper:
                continue
            # At least one end is listed (unlisted nodes share the first host): report there.
            node = spec.lower if spec.lower in self.placed else spec.upper
            _, path, at = self.placed[node]
            self.ctx.add(
                at,
                path,
                "the two ends of an air link with a radio on one host",
                f"{spec.lower} on host {lower!r}, {spec.upper} on host {upper!r} ({spec.name})",
                f"the gNB's NR slots are scheduled in one relay on its host; put "
                f"{spec.lower} on host {upper!r} with {spec.upper}",
            )

    def _qos(self, qos: Section | None) -> model.Qos | None:
        """The sessions' QoS flows; None when a rule or the default names a QFI the flows lack
        (reported: a G-PDU would carry a flow its session does not have)."""
        if qos is None:
            return model.Qos()
        if not qos.clean:
            return None
        flows = tuple(qos["flows"])
        known = ", ".join(str(q) for q in flows)
        ok = True
        if qos["default_qfi"] not in flows:
            self.ctx.add(
                qos.at("default_qfi"),
                qos.path_of("default_qfi"),
                f"a QFI of the sessions' flows ({known})",
                f"QFI {qos['default_qfi']}",
                "add it to qos.flows",
            )
            ok = False
        rules: list[model.QosRule] = []
        written: Items | None = qos.get("rules")
        for i, rule, _ in written.good() if written is not None else ():
            if rule["qfi"] not in flows:
                self.ctx.add(
                    rule.at("qfi"),
                    rule.path_of("qfi"),
                    f"a QFI of the sessions' flows ({known})",
                    f"unknown QFI {rule['qfi']} (rule {i})",
                    "add it to qos.flows, or map the rule to one of them",
                )
                ok = False
                continue
            rules.append(
                model.QosRule(
                    rule["qfi"], rule.get("dscp"), tuple(rule.get("ports") or ()), rule.get("dds")
                )
            )
        if not ok:
            return None
        if written is None:  # the default rules whose flow the sessions have
            rules = [r for r in model.Qos().rules if r.qfi in flows]
        return model.Qos(flows, qos["default_qfi"], tuple(rules))

    def _check_cell_form(self, cell: Section) -> None:
        """A cell has a core, or a UPF and an edge (see `model.Cell`), never a mix."""
        has = {k: cell.written(k) for k in ("core", "upf", "edge")}
        if has["core"] and (has["upf"] or has["edge"]):
            key = "upf" if has["upf"] else "edge"
            self.ctx.add(
                cell.at(key),
                cell.path_of(key),
                "either core (a router hosting the edge server) or upf and edge (the 5G core "
                "path), not both",
                f"{key} beside core {cell['core']!r}",
                "drop core to tunnel this cell's traffic over N3 to the UPF",
            )
        elif has["upf"] != has["edge"]:
            there, missing = ("upf", "edge") if has["upf"] else ("edge", "upf")
            self.ctx.add(
                cell.at(there),
                cell.path_of(there),
                f"{there} together with {missing}",
                f"{there} without {missing}",
                "the UPF sends the cell's traffic over N6 to an edge server; name both",
            )
        elif not has["core"] and not has["upf"]:
            self.ctx.add(
                cell.node,
                cell.path,
                "a cell with core, or with upf and edge",
                "neither",
                "e.g. {gnb: gnb1, upf: upf1, edge: edge1}",
            )

    def _check_shared_edges(self, cells: Items | None) -> None:
        """An edge server shared by cells sits in one place (behind one UPF, or at cells)."""
        first: dict[str, tuple[str, str]] = {}  # edge -> (where it is, the path that said so)
        for _, cell, _ in cells.good() if cells else ():
            edge = _edge_name(cell)
            if edge is None or not cell.written("upf"):
                continue
            where = (
                "placement cell" if channel.placement(cell) == "cell" else f"behind {cell['upf']}"
            )
            if edge not in first:
                first[edge] = (where, cell.path_of("edge"))
            elif first[edge][0] != where:
                self.ctx.add(
                    cell.at("edge"),
                    cell.path_of("edge"),
                    f"edge {edge!r} where {first[edge][1]} puts it ({first[edge][0]})",
                    where,
                    "an edge server has one place; give this cell an edge of its own",
                )

    def _cell(self, cell: Section) -> model.Cell:
        """A cell, its scheduler written as its own field or in its `radio` (not both)."""
        built: model.Cell = schema_v1.CELL.build(cell)
        if cell.written("site"):
            built = dataclasses.replace(built, site=channel.site(cell))  # type: ignore[arg-type]
        if cell.written("edge"):
            built = dataclasses.replace(
                built, edge=_edge_name(cell), placement=channel.placement(cell)
            )
        radio = cell.get("radio")
        if not isinstance(radio, Section) or "scheduler" not in radio:
            return built
        if cell.written("scheduler") and cell["scheduler"] != radio["scheduler"]:
            self.ctx.add(
                radio.at("scheduler"),
                radio.path_of("scheduler"),
                f"the cell's scheduler ({cell['scheduler']}, at {cell.path_of('scheduler')}) "
                "or no scheduler here",
                repr(radio["scheduler"]),
                "write the scheduler in one place",
            )
        return dataclasses.replace(built, scheduler=radio["scheduler"])

    def _check_links_named(self, section: Section, key: str) -> None:
        """Each link a list at `section[key]` names is a link of the topology."""
        names = section.get(key)
        if not isinstance(names, Items) or not self.topology_ok:
            return
        for i, name, node in names.good():
            if name not in self.link_kinds:
                self._unknown_link(node, item(names.path, i), name)

    def _unknown_link(self, node: Node, path: str, name: str) -> None:
        """Report `name` as no link of the topology, with the likeliest one it meant."""
        lower, _, upper = name.partition("-")
        reversed_name = f"{upper}-{lower}"
        hint = (
            f"links are named lower-upper (vehicle-gnb, gnb-core): {reversed_name}"
            if reversed_name in self.link_kinds
            else did_you_mean(name, list(self.link_kinds), NAME_CUTOFF)
        )
        self.ctx.add(
            node,
            path,
            f"the name of a link of this topology ({_listing(list(self.link_kinds))})",
            repr(name),
            hint,
        )

    def _check_link(self, section: Section, key: str) -> bool:
        """Whether `section[key]` names a link of the topology (reported when it does not)."""
        name = section.get(key)
        if name is None:
            return False
        if name in self.link_kinds:
            return True
        if self.topology_ok:
            self._unknown_link(section.at(key), section.path_of(key), name)
        return False

    def _check_node(self, section: Section, key: str) -> None:
        name = section.get(key)
        if name is None or name in self.roles or not self.topology_ok:
            return
        self.ctx.add(
            section.at(key),
            section.path_of(key),
            f"the name of a node of this topology ({_listing(list(self.roles))})",
            repr(name),
            did_you_mean(name, list(self.roles), NAME_CUTOFF),
        )

    # -- links --

    def _links(self) -> model.Links | None:
        links: Section | None = self.root.get("links")
        defaults: dict[str, dict[str, dict[str, object]]] = {
            kind: {"uplink": {}, "downlink": {}} for kind in LINK_KINDS
        }
        merged: dict[str, dict[str, dict[str, object]]] = {}
        # Where each radio was written last (the section holding its `radio` key): the air
        # defaults by direction, the overrides by link and direction.
        where: dict[tuple[str, str], Section] = {}
        rrc: dict[str, RrcSettings | None] = {}  # "air" (the default) or a link -> settings
        if links is not None:
            air: Section | None = links.get("air")
            if air is not None and air.written("rrc"):
                rrc["air"] = _rrc(air.get("rrc"))
            for kind in LINK_KINDS:
                pair: Section | None = links.get(kind)
                if kind == "n3" and pair is None:
                    pair = links.get("backhaul")  # the gNB's wired link, whatever its far end
                both = _radio(pair.get("radio"), pair, self.ctx, check=False) if pair else None
                for direction in ("uplink", "downlink"):
                    profile = pair.get(direction) if pair else None
                    base = both if isinstance(both, Radio) else None
                    changes = (
                        profile_changes(profile, self.ctx, base, check_radio=False)
                        if profile
                        else {}
                    )
                    if profile is not None and "radio" in profile:
                        where[kind, direction] = profile
                    elif pair is not None and "radio" in pair:
                        changes["radio"] = base
                        where[kind, direction] = pair
                    defaults[kind][direction] = changes
            overrides: Items | None = links.get("overrides")
            seen: dict[str, str] = {}
            for _, override, _ in overrides.good() if overrides else ():
                if not self._check_link(override, "link"):
                    continue
                name = override["link"]
                if name in seen:
                    self.ctx.add(
                        override.at("link"),
                        override.path_of("link"),
                        "one override per link (put all its fields in one entry)",
                        f"{name!r} again (also at {seen[name]})",
                    )
                    continue
                seen[name] = override.path
                kind = self.link_kinds[name]
                if override.written("rrc"):
                    if kind == "air":
                        rrc[name] = _rrc(override.get("rrc"))
                    else:
                        self.ctx.add(
                            override.at("rrc"),
                            override.path_of("rrc"),
                            "rrc on an air link only (RRC states are a UE's)",
                            f"rrc on {name}, a {kind} link",
                        )
                merged[name] = {}
                for d in ("uplink", "downlink"):
                    if d not in override:
                        merged[name][d] = {}
                        continue
                    base = defaults[kind][d].get("radio")
                    merged[name][d] = profile_changes(
                        override[d],
                        self.ctx,
                        base if isinstance(base, Radio) else None,
                        check_radio=False,
                    )
                    if "radio" in override[d]:
                        where[name, d] = override[d]
        if not self.topology_ok or self.ctx.issues:
            return None
        specs = []
        for name, kind in self.link_kinds.items():
            lower, upper = name.split("-")
            states = rrc.get(name, rrc.get("air")) if kind == "air" else None
            profiles = {
                d: LinkProfile(
                    **{**defaults[kind][d], **merged.get(name, {}).get(d, {}), "rrc": states}
                )
                for d in ("uplink", "downlink")
            }
            for d in ("uplink", "downlink"):
                if (name, d) not in where and (kind, d) in where:
                    where[name, d] = where[kind, d]
            specs.append(
                model.LinkSpec(name, kind, lower, upper, profiles["uplink"], profiles["downlink"])  # type: ignore[arg-type]
            )
        specs = self._cell_radios(specs, where)
        if specs is None or not self._radios_fit(specs, where):
            return None
        if not self._one_grid_per_cell(specs, where):
            return None
        backend = links.get("backend", "auto") if links is not None else "auto"
        with_radio = [s.name for s in specs if s.uplink.radio or s.downlink.radio]
        if backend == "tc" and with_radio and links is not None:
            self.ctx.add(
                links.at("backend"),
                links.path_of("backend"),
                "userspace or auto for links with a radio",
                f"tc, with a radio on {', '.join(with_radio)}",
                "the NR slot model runs in the userspace relay; tc's qdiscs have no slot clock",
            )
        with_rrc = [s.name for s in specs if s.uplink.rrc is not None]
        if backend == "tc" and with_rrc and links is not None:
            self.ctx.add(
                links.at("backend"),
                links.path_of("backend"),
                "userspace or auto for air links with rrc",
                f"tc, with RRC states on {', '.join(with_rrc)}",
                "the relay holds a quiet UE's first packet back; a qdisc cannot",
            )
            return None
        self.link_specs = {s.name: s for s in specs}
        return model.Links(backend=backend, links=tuple(specs))

    def _cells(self) -> list[Section]:
        topo: Section | None = self.root.get("topology")
        cells: Items | None = topo.get("cells") if topo else None
        return [c for _, c, _ in cells.good()] if cells else []

    def _cell_radios(
        self, specs: list[model.LinkSpec], where: dict[tuple[str, str], Section]
    ) -> list[model.LinkSpec] | None:
        """`specs` with each cell's `radio` (its slot grid and carrier) laid over its air
        links' radios; None when one does not fit (reported)."""
        out = {s.name: s for s in specs}
        for cell in self._cells():
            if "radio" not in cell:
                continue
            value = cell["radio"]
            part, profile = radios.cell_part(value.values if isinstance(value, Section) else value)
            mine = [s for s in specs if s.kind == "air" and s.upper == cell["gnb"]]
            for spec in mine:
                changed = {}
                for d in ("uplink", "downlink"):
                    radio = radios.with_cell(getattr(spec, d).radio, part, profile)
                    changed[d] = dataclasses.replace(getattr(spec, d), radio=radio)
                    if radio is not None:
                        where[spec.name, d] = cell
                out[spec.name] = dataclasses.replace(spec, **changed)
            if profile is None and all(
                s.uplink.radio is None and s.downlink.radio is None for s in mine
            ):
                self.ctx.add(
                    cell.at("radio"),
                    cell.path_of("radio"),
                    "air links with a radio (links.air.radio) for the cell's part to change, "
                    "or a `profile` here",
                    f"no radio on {', '.join(s.name for s in mine) or 'any air link of it'}",
                )
                return None
        return [out[s.name] for s in specs]

    def _radios_fit(
        self, specs: list[model.LinkSpec], where: dict[tuple[str, str], Section]
    ) -> bool:
        """Whether every link direction's radio, all its layers laid, has fields that fit
        together; each misfit is reported once, where its radio was written last."""
        said: set[str] = set()
        for spec in specs:
            for d in ("uplink", "downlink"):
                radio = getattr(spec, d).radio
                why = None if radio is None else radios.problem(radio)
                section = where.get((spec.name, d))
                if why is None or section is None or section.path in said:
                    continue
                said.add(section.path)
                _misfit(self.ctx, section, f"on {spec.name} {d}: {why}")
        return not said

    def _one_grid_per_cell(
        self, specs: list[model.LinkSpec], where: dict[tuple[str, str], Section]
    ) -> bool:
        """Whether the radios of each gNB's air links share one slot grid (reported where
        the first that does not was written)."""
        for d in ("uplink", "downlink"):
            first: dict[str, tuple[str, Radio]] = {}
            for spec in specs:
                radio = getattr(spec, d).radio
                if spec.kind != "air" or radio is None:
                    continue
                if spec.upper not in first:
                    first[spec.upper] = (spec.name, radio)
                    continue
                name, other = first[spec.upper]
                if radios.grid(radio) == radios.grid(other):
                    continue
                section = where.get((spec.name, d))
                if section is None:  # pragma: no cover - a differing radio was written somewhere
                    continue
                self._off_grid(
                    section, spec, d, radio, (name, other),
                    "put the cell's TDD pattern and numerology in topology.cells[].radio",
                )  # fmt: skip
                return False
        return True

    # -- timeline --

    def _timeline(self) -> list[model.Event]:
        events: Items | None = self.root.get("timeline")
        out: list[model.Event] = []
        radio_sets: list[tuple[model.SetEvent, Section]] = []
        for _, event, node in events.good() if events else ():
            if event.tag is None:
                continue
            built = self._event(event, node.start_mark.line + 1)
            if isinstance(built, model.SetEvent) and "radio" in event:
                radio_sets.append((built, event))
            elif built is not None:
                out.append(built)
        return out + self._radio_sets(radio_sets)

    def _radio_sets(self, sets: list[tuple[model.SetEvent, Section]]) -> list[model.Event]:
        """`set` events with their radios: in time order, a mapping changes the radio the
        link has then (its profile's, or the last `set`'s). Where the two directions of a
        `both` event end up with different radios, it becomes one event per direction. A
        radio that leaves its cell's slot grid is refused: one gNB, one grid."""
        if not self.link_specs:
            return []  # the links did not check out: reported there
        now = {(s.name, d): s.profile(d).radio for s in self.link_specs.values() for d in DIRS}
        out: list[model.Event] = []
        for event, section in sorted(sets, key=lambda p: (p[0].at_s, p[0].line)):
            if event.link not in self.link_specs:
                continue  # an unknown link: the event's own check reported it
            directions = DIRS if event.direction == "both" else (event.direction,)
            built: dict[str, Radio | None] = {}
            for d in directions:
                radio = _radio(section["radio"], section, self.ctx, now[event.link, d])
                if radio is False:
                    break
                assert radio is not True
                if not self._grid_kept(event.link, d, radio, now, section):
                    break
                built[d] = radio
            else:
                for d, radio in built.items():
                    now[event.link, d] = radio
                values = list(built.values())
                if len(values) == 1 or values[0] == values[1]:
                    changes = {**event.changes, "radio": values[0]}
                    out.append(dataclasses.replace(event, changes=changes))
                else:
                    out += [
                        dataclasses.replace(
                            event, direction=d, changes={**event.changes, "radio": r}
                        )
                        for d, r in built.items()
                    ]
        return out

    def _grid_kept(
        self,
        link: str,
        direction: str,
        radio: Radio | None,
        now: dict[tuple[str, str], Radio | None],
        section: Section,
    ) -> bool:
        """Whether `radio` on `link` keeps the slot grid of the other UEs of its cell."""
        spec = self.link_specs[link]
        if spec.kind != "air" or radio is None:
            return True
        for other in self.link_specs.values():
            theirs = now[other.name, direction]
            if other.name == link or other.upper != spec.upper or theirs is None:
                continue
            if radios.grid(theirs) != radios.grid(radio):
                self._off_grid(
                    section, spec, direction, radio, (f"{other.name} then", theirs),
                    "a set event changes one UE; a cell's TDD pattern stays as it started",
                )  # fmt: skip
                return False
        return True

    def _off_grid(
        self,
        section: Section,
        spec: model.LinkSpec,
        direction: str,
        radio: Radio,
        cell_radio: tuple[str, Radio],
        hint: str,
    ) -> None:
        """Report `radio` on `spec` as off the slot grid its cell's other UEs have
        (`cell_radio`: where that grid was seen, and a radio with it)."""
        seen_on, other = cell_radio
        self.ctx.add(
            section.at("radio"),
            section.path_of("radio"),
            f"the slot grid of cell {spec.upper} ({radios.grid_text(other)}, as on "
            f"{seen_on}): one gNB, one slot grid for all its UEs",
            f"{radios.grid_text(radio)} on {spec.name} {direction}",
            hint,
        )

    def _check_time(self, event: Section) -> None:
        at = event.get("at")
        if at is None or self.duration is None or at <= self.duration:
            return
        self.ctx.add(
            event.at("at"),
            event.path_of("at"),
            f"a time within the run (0s to duration {units.format_duration(self.duration)})",
            repr(event.at("at").value),
        )

    def _event(self, event: Section, line: int) -> model.Event | None:
        self._check_time(event)
        at = event.get("at")
        if event.tag == "set":
            self._check_link(event, "set")
            if not event.clean:
                return None
            changes = profile_changes(event, self.ctx, with_radio=False)  # see _radio_sets
            return model.SetEvent(at, event["set"], event["direction"], changes, line=line)
        if event.tag == "shape":
            self._check_node(event, "shape")
            if not event.clean:
                return None
            return model.ShapeEvent(
                at, event["shape"], event.get("uplink"), event.get("downlink"), line=line
            )
        if event.tag == "clear":
            self._check_node(event, "clear")
            return model.ClearEvent(at, event["clear"], line=line) if event.clean else None
        if event.tag == "outage":
            self._check_link(event, "outage")
            length = event.get("for")
            known = at is not None and length is not None and self.duration is not None
            if known and at <= self.duration < at + length:
                self.ctx.add(
                    event.at("for"),
                    event.path_of("for"),
                    "an outage that ends by the end of the run "
                    f"({units.format_duration(self.duration)})",
                    f"{event.at('for').value!r} (ending at {units.format_duration(at + length)})",
                )
            return (
                model.OutageEvent(at, event["outage"], length, line=line) if event.clean else None
            )
        return self._trace(event, line)

    def _trace(self, event: Section, line: int) -> model.TraceEvent | None:
        self._check_link(event, "trace")
        file = event.get("file")
        if file is None:
            return None
        path = self.base_dir / file
        shown = str(self.display_dir / file)
        fmt = event.get("format") or default_format(file)
        expected = f"an existing {fmt} trace file (relative to the scenario file)"
        if not path.is_file():
            why = "a directory" if path.is_dir() else "no such file"
            self.ctx.add(event.at("file"), event.path_of("file"), expected, f"{file!r} ({why})")
            return None
        try:
            text = path.read_text(encoding="utf-8", errors="replace")
        except OSError as err:
            self.ctx.add(
                event.at("file"), event.path_of("file"), expected, f"{file!r} ({err.strerror})"
            )
            return None
        problems = _trace_problems(text, fmt)
        where = event.at("file").start_mark
        for problem in problems:
            self.ctx.add(
                None,
                event.path_of("file"),
                f"{problem.expected} ({fmt} trace)",
                problem.found,
                f"trace named at {self.ctx.file}:{where.line + 1}:{where.column + 1}",
                file=shown,
                line=problem.line,
            )
        if problems or not event.clean:
            return None
        return model.TraceEvent(
            event["at"],
            event["trace"],
            event["direction"],
            path.resolve(),
            fmt,
            loop=event["loop"],
            line=line,
        )

    # -- workload --

    def _workload(self) -> model.Workload:
        workload: Section | str | None = self.root.get("workload")
        if workload is None:
            return model.Workload()
        if isinstance(workload, str):  # `workload: none` or `workload: edgeloc`
            return model.Workload(kind=workload)  # type: ignore[arg-type]
        changes: dict[str, Any] = {}
        dataset = workload.get("dataset")
        if workload.written("dataset") and dataset != "synthetic" and dataset is not None:
            folder = self.base_dir / dataset
            if folder.is_dir():
                changes["dataset"] = folder.resolve()
            else:
                self.ctx.add(
                    workload.at("dataset"),
                    workload.path_of("dataset"),
                    "'synthetic' or an existing folder of recorded data (relative to the "
                    "scenario file)",
                    f"{dataset!r} ({'a file' if folder.exists() else 'no such folder'})",
                )
        weights = workload.get("weights")
        if weights is not None:
            file = self.base_dir / weights
            if file.is_file():
                changes["weights"] = file.resolve()
            else:
                self.ctx.add(
                    workload.at("weights"),
                    workload.path_of("weights"),
                    "null or an existing weights file (relative to the scenario file)",
                    f"{weights!r} (no such file)",
                )
        learner: Section | None = workload.get("learner")
        splits = workload.get("splits")
        fixed = learner.get("fixed_split") if learner is not None else None
        if fixed is not None and splits is not None and fixed not in splits:
            assert learner is not None
            self.ctx.add(
                learner.at("fixed_split"),
                learner.path_of("fixed_split"),
                f"one of the splits listed in workload.splits ({_listing(list(splits))})",
                repr(fixed),
                did_you_mean(fixed, list(splits), NAME_CUTOFF),
            )
        fusion: Section | None = workload.get("fusion")
        if (
            isinstance(fusion, Section)
            and fusion.get("correlation") is not None
            and fusion.get("method", "paper") != "ekf"
        ):
            self.ctx.add(
                fusion.at("correlation"),
                fusion.path_of("correlation"),
                "no correlation with the paper's fusion (it weighs answers by latency only): "
                "method: ekf, or no correlation",
                f"correlation with method {fusion.get('method', 'paper')!r}",
            )
        if isinstance(fusion, Section) and fusion.get("robust_centre") is not None:
            # robust defaults to 2 (model.Fusion): only a written null switches it off.
            no_robust = fusion.written("robust") and fusion.get("robust") is None
            method = fusion.get("method", "paper")
            if no_robust or method != "paper":
                self.ctx.add(
                    fusion.at("robust_centre"),
                    fusion.path_of("robust_centre"),
                    "robust_centre only with the paper's fusion and a robust weight (it centres"
                    " that weight): method: paper and robust set, or no robust_centre",
                    "robust: null" if no_robust else f"robust_centre with method {method!r}",
                )
        if isinstance(fusion, Section) and fusion.get("confidence"):
            method = fusion.get("method", "paper")
            if method != "paper":
                self.ctx.add(
                    fusion.at("confidence"),
                    fusion.path_of("confidence"),
                    "confidence only with the paper's fusion (it scales that weight): method:"
                    " paper, or no confidence",
                    f"confidence with method {method!r}",
                )
            else:
                from nodes.edgeloc.fusion import ConfidenceMissing, ConfidenceWeight
                from nodes.edgeloc.settings import confidence_file

                calibration = confidence_file(changes.get("weights"))
                try:
                    ConfidenceWeight.read(calibration)
                except ConfidenceMissing as e:
                    self.ctx.add(
                        fusion.at("confidence"),
                        fusion.path_of("confidence"),
                        "a confidence calibration beside the weights (`python -m"
                        " nodes.edgeloc.train --calibrate --out DIR` writes it)",
                        str(e),
                    )
        if not workload.clean or self.ctx.issues:
            return model.Workload()
        built: model.Workload = schema_v1.WORKLOAD.build(workload)
        return dataclasses.replace(built, **changes)
