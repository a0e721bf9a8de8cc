"""Names in a run folder and the topics recorded into its `run.mcap`.

A run folder (`runs/<id>/`, the user's results) holds `run.mcap` and, while the run goes,
`parts/<process>.mcap` with `parts/manifest.json`; beside them the orchestrator's files. These
names are written by the orchestrator, attached to `run.mcap` by the merge and read back by the
report, so they are spelled once, here.
"""

from __future__ import annotations

from pathlib import Path

RUN_MCAP = "run.mcap"
PARTS_DIR = "parts"
MANIFEST = "manifest.json"
#: The scenario as run (a copy of the YAML).
SCENARIO_FILE = "scenario.yaml"
#: What the orchestrator measured and decided (`testbed.run.RunResult`): paths to the edge,
#: apps, cross-traffic, captures, the timeline's start. Written as the run ends, just before
#: the recording is finalised, so a run that ends normally has it attached.
RUN_FILE = "run.json"
#: The link self-test's measurements (`testbed.linktest.LinkTestReport.to_dict`).
LINKTEST_FILE = "linktest.json"
#: Per link and direction, the profile applied at the start and left at the end.
LINKS_CONFIG_FILE = "links.json"
#: One JSON line per timeline event as the player applied it.
EVENTS_FILE = "events.jsonl"
#: Folder of a run's packet captures (`record.pcap`): <link>.pcapng each.
PCAP_DIR = "pcap"
#: The nodes' settings (`nodes.edgeloc.settings.config_to_dict` of the run's ReplayConfig):
#: the report replays the drive with them (fixed splits and the oracle beside the learner).
NODE_CONFIG_FILE = "nodes/config.json"
#: The drive's camera frames rendered ahead for the sensors (`nodes.edgeloc.frames`); removed
#: when the nodes stop (tens of MB).
FRAMES_FILE = "nodes/frames.npy"
#: The run's common start time, which the vehicles' sensors wait for (`nodes.ros.start`).
START_FILE = "nodes/start.json"
#: The report's machine-readable figures.
SUMMARY_FILE = "summary.json"
#: Files of the run folder attached to run.mcap, when the run wrote them (a name with a
#: folder is attached under that same relative name).
ATTACHED_FILES = (
    SCENARIO_FILE,
    LINKTEST_FILE,
    LINKS_CONFIG_FILE,
    EVENTS_FILE,
    NODE_CONFIG_FILE,
    RUN_FILE,
)

LINK_EVENTS_TOPIC = "/links/events"
LINK_COUNTERS_TOPIC = "/links/counters"
#: The vehicles' handovers between cells, as applied (`channel.handover` scenarios).
HANDOVER_TOPIC = "/handover"
#: The per-vehicle topics the report reads, by their last path element.
VEHICLE_TOPICS = ("gt", "vo", "dnn_answer", "pose", "split_decision", "detector", "inference")


def radio_topic(vehicle: str) -> str:
    """Where a vehicle's channel steps are recorded (`channel:` scenarios), e.g. `/radio/av1`."""
    return f"/radio/{vehicle}"


def vehicle_topic(vehicle: str, name: str) -> str:
    """A vehicle's topic, e.g. `/av1/pose`."""
    return f"/{vehicle}/{name}"


def parts_dir(folder: Path) -> Path:
    return Path(folder) / PARTS_DIR


def part_path(folder: Path, process: str) -> Path:
    """Where process `process` (e.g. `av1.fusion`, `orchestrator`) writes its part."""
    return parts_dir(folder) / f"{process}.mcap"
