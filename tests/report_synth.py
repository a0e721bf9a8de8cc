"""Synthetic run.mcap files for the report tests, written the way the recorder writes them:
profile ros2, CDR messages, `ros2msg` schemas built from nodes/edgeloc_interfaces/msg (with
builtin_interfaces/Time appended rosbag2-style), metadata values JSON-encoded, attachments."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType
from mcap_ros2.writer import Writer

from netem.nr.radio import Radio
from netem.profile import LinkProfile
from nodes.recording.layout import LINKS_CONFIG_FILE

MSG_DIR = Path(__file__).resolve().parents[1] / "nodes" / "edgeloc_interfaces" / "msg"
PKG = "edgeloc_interfaces"
SEP = "=" * 80
TIME_MSG = "int32 sec\nuint32 nanosec\n"

# The InferenceResult fields the report reads, for as long as the interfaces package does not
# carry the .msg yet (the recorder's contract names these fields).
INFERENCE_RESULT_FALLBACK = """builtin_interfaces/Time stamp
string vehicle
uint32 frame_id
string split
uint8 split_index
uint64 payload_bytes
float64 head_s
float64 edge_compute_s
float64 latency_s
bool ok
bool timed_out
string error
"""


def schema_text(name: str) -> str:
    """The ros2msg schema text of edgeloc_interfaces/msg/<name> with its dependencies."""
    path = MSG_DIR / f"{name}.msg"
    if path.is_file():
        text = path.read_text()
    elif name == "InferenceResult":
        text = INFERENCE_RESULT_FALLBACK
    else:
        raise FileNotFoundError(path)
    return f"{text.rstrip()}\n{SEP}\nMSG: builtin_interfaces/Time\n{TIME_MSG}"


def stamp(t: float) -> dict[str, int]:
    sec = math.floor(t)
    return {"sec": int(sec), "nanosec": round((t - sec) * 1e9)}


@dataclass
class SynthRun:
    """Messages, metadata and attachments of one synthetic recording."""

    messages: list[tuple[float, str, str, dict[str, Any]]] = field(default_factory=list)
    metadata: dict[str, dict[str, Any]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)

    def add(self, log_t: float, topic: str, msg_type: str, msg: dict[str, Any]) -> None:
        self.messages.append((log_t, topic, msg_type, msg))

    def pose(
        self,
        topic: str,
        t: float,
        frame: int,
        method: str,
        x: float,
        y: float,
        yaw: float = 0.0,
        latency: float = math.nan,
        log_t: float | None = None,
        vehicle: str = "av1",
    ) -> None:
        self.add(
            t + 0.001 if log_t is None else log_t,
            topic,
            "PoseEstimate",
            {
                "stamp": stamp(t),
                "vehicle": vehicle,
                "method": method,
                "x": x,
                "y": y,
                "yaw": yaw,
                "latency_s": latency,
                "frame_id": frame,
                "entropy_nats": math.nan,
            },
        )

    def decision(
        self, t: float, frame: int, split: str, arms: list[str], plays: int, rule: str = "ucb"
    ) -> None:
        """av1's SplitDecision for a request that starts at `t` (no UCB statistics)."""
        n = len(arms)
        self.add(
            t,
            "/av1/split_decision",
            "SplitDecision",
            {
                "stamp": stamp(t),
                "vehicle": "av1",
                "frame_id": frame,
                "chosen": split,
                "chosen_index": arms.index(split),
                "rule": rule,
                "arm_names": arms,
                "arm_n": [0] * n,
                "arm_mean": [math.nan] * n,
                "arm_var": [math.nan] * n,
                "arm_index": [-math.inf] * n,
                "last_latency_s": math.nan,
                "plays": plays,
                "plays_total": plays,
            },
        )

    def inference(
        self,
        t: float,
        frame: int,
        split: str,
        arms: list[str],
        latency: float,
        ok: bool,
        timed_out: bool,
        error: str = "",
        payload: int = 1000,
        head_s: float = 0.001,
    ) -> None:
        """av1's InferenceResult, stamped (and logged) at `t`."""
        self.add(
            t,
            "/av1/inference",
            "InferenceResult",
            {
                "stamp": stamp(t),
                "vehicle": "av1",
                "frame_id": frame,
                "split": split,
                "split_index": arms.index(split),
                "payload_bytes": payload,
                "head_s": head_s,
                "edge_compute_s": 0.001 if ok else math.nan,
                "latency_s": latency,
                "ok": ok,
                "timed_out": timed_out,
                "error": error,
            },
        )

    def radio(
        self,
        t: float,
        cell: str,
        ul_mcs: int,
        x: float = 0.0,
        y: float = 0.0,
        sinr_db: float = 10.0,
        vehicle: str = "av1",
        mcs: int = 15,
        bler: float = 0.1,
        ul_bler: float = 0.1,
    ) -> None:
        """The vehicle's RadioState of the channel step at `t` (CQI 9; downlink MCS 15 and
        both BLERs 0.1 unless given)."""
        self.add(
            t,
            f"/radio/{vehicle}",
            "RadioState",
            {
                "stamp": stamp(t),
                "vehicle": vehicle,
                "cell": cell,
                "x": x,
                "y": y,
                "rsrp_dbm": -90.0,
                "sinr_db": sinr_db,
                "cqi": 9,
                "mcs": mcs,
                "bler": bler,
                "ul_sinr_db": sinr_db - 5.0,
                "ul_mcs": ul_mcs,
                "ul_bler": ul_bler,
            },
        )

    def handover(
        self,
        t: float,
        source: str,
        target: str,
        scheduled_s: float,
        interruption_s: float,
        lossless: bool,
        lateness_s: float = 0.02,
        error: str = "",
        vehicle: str = "av1",
    ) -> None:
        """A Handover on /handover as the recorder writes it: stamped when it took effect."""
        self.add(
            t,
            "/handover",
            "Handover",
            {
                "stamp": stamp(t),
                "vehicle": vehicle,
                "source": source,
                "target": target,
                "scheduled_s": scheduled_s,
                "lateness_s": lateness_s,
                "interruption_s": interruption_s,
                "lossless": lossless,
                "error": error,
            },
        )

    def channel_run(
        self, run_id: str, sites: dict[str, tuple[float, float]], handover: Any = None
    ) -> None:
        """run.json's metadata of a run with a UMa channel stepped every 100 ms: its cell
        `sites` (gNB -> x, y in metres) and its `handover` settings (None: no handovers)."""
        self.metadata["edgeloc.run"] = {
            "run_id": run_id,
            "status": "ok",
            "channel": {
                "model": "UMa",
                "los": "auto",
                "step_s": 0.1,
                "trace": None,
                "sites": [{"name": n, "x": x, "y": y} for n, (x, y) in sites.items()],
                "handover": handover,
            },
        }

    def links(self, radios: dict[str, Radio | None], backend: str = "userspace") -> None:
        """Attach links.json as `testbed.recording.links_config` writes it: per link (name ->
        its radio, None for a backhaul link) both directions' `LinkProfile.to_dict`, the radio
        serialised inside as the run serialises it."""
        config = {
            "backend": backend,
            "links": {
                name: {
                    "kind": "air" if radio is not None else "backhaul",
                    "lower": name.split("-")[0],
                    "upper": name.split("-")[-1],
                    "profiles": {
                        d: LinkProfile(delay_s=0.001, radio=radio).to_dict()
                        for d in ("uplink", "downlink")
                    },
                }
                for name, radio in radios.items()
            },
        }
        self.attachments[LINKS_CONFIG_FILE] = json.dumps(config).encode()

    def write(self, path: Path, chunk_size: int = 1024 * 1024, finish: bool = True) -> Path:
        """Write the file; `finish=False` leaves it as a killed recorder would (no footer)."""
        f = open(path, "wb")  # noqa: SIM115 - left unfinished on purpose when finish=False
        w = Writer(f, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        schemas: dict[str, Any] = {}
        for log_t, topic, msg_type, msg in sorted(self.messages, key=lambda m: m[0]):
            if msg_type not in schemas:
                schemas[msg_type] = w.register_msgdef(
                    f"{PKG}/msg/{msg_type}", schema_text(msg_type)
                )
            ns = round(log_t * 1e9)
            w.write_message(topic, schemas[msg_type], msg, log_time=ns, publish_time=ns)
        for name, data in self.metadata.items():
            w.add_metadata(
                name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in data.items()}
            )
        for name, data in self.attachments.items():
            w.add_attachment(0, 0, name, "application/octet-stream", data)
        if finish:
            w.finish()
        f.close()
        return path
