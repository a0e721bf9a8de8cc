"""The split learner's choices grouped by the radio each request met.

With a scenario `channel:` the uplink's MCS follows the vehicle's place, not the clock, so
"phases between timeline events" no longer say what the network was. Instead each play is put
in the band of the uplink MCS at the instant its request was sent, and per band the report
says how the learner chose: plays, the share of each split, and the mean payload it sent (a
learner that follows the radio sends less where the MCS is low). Around each handover
(`around`), the same figures in the `AROUND_S` before and after it, with EdgeLoc's error and
the uplink MCS there: what the cell edge and the interruption did to the learner and to the
fused pose. Pure: numbers in, a table out; `testbed.replay` and `reports.sections.radio` both
use it.
"""

from __future__ import annotations

import bisect
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

#: Bands of the uplink MCS (TS 38.214 Table 5.1.3.1-1, 0..28): QPSK-ish cell edge, the
#: middle, and 64QAM near the mast.
MCS_BANDS: tuple[tuple[int, int], ...] = ((0, 9), (10, 19), (20, 28))


def band_of(mcs: int, bands: Sequence[tuple[int, int]] = MCS_BANDS) -> int:
    """The index of the band holding `mcs` (bands are contiguous and sorted)."""
    index = bisect.bisect_right([lo for lo, _ in bands], mcs) - 1
    if index < 0 or mcs > bands[index][1]:
        raise ValueError(f"MCS {mcs} is in none of the bands {list(bands)}")
    return index


def by_band(
    mcs_at_play: Sequence[int],
    splits: Sequence[str],
    payload_bytes: Mapping[str, float],
    time_share: Sequence[float] | None = None,
    bands: Sequence[tuple[int, int]] = MCS_BANDS,
) -> list[dict[str, Any]]:
    """One row per band: {mcs (lo, hi), time_share (of the run, when given), plays, share
    {split: fraction of the band's plays}, mean_payload_bytes (None: no plays)}.

    `mcs_at_play[i]` is the uplink MCS when play i was sent and `splits[i]` its split;
    `payload_bytes` the mean bytes each split sends."""
    if len(mcs_at_play) != len(splits):
        raise ValueError(f"{len(mcs_at_play)} MCS values for {len(splits)} plays")
    rows = []
    grouped: list[list[str]] = [[] for _ in bands]
    for mcs, split in zip(mcs_at_play, splits, strict=True):
        grouped[band_of(mcs, bands)].append(split)
    for k, ((lo, hi), chosen) in enumerate(zip(bands, grouped, strict=True)):
        count = Counter(chosen)
        sent = [payload_bytes[s] for s in chosen if s in payload_bytes]
        rows.append(
            {
                "mcs": [lo, hi],
                "time_share": None if time_share is None else time_share[k],
                "plays": len(chosen),
                "share": {s: n / len(chosen) for s, n in count.most_common()},
                "mean_payload_bytes": sum(sent) / len(sent) if sent else None,
            }
        )
    return rows


def time_shares(
    mcs_per_step: Sequence[int], bands: Sequence[tuple[int, int]] = MCS_BANDS
) -> list[float]:
    """The share of the run's channel steps in each band."""
    counts = Counter(band_of(m, bands) for m in mcs_per_step)
    total = max(1, len(mcs_per_step))
    return [counts[k] / total for k in range(len(bands))]


def lines(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """What `testbed replay` prints: one line per band with plays."""
    out = []
    for row in rows:
        lo, hi = row["mcs"]
        share = row["time_share"]
        when = f" ({share:.0%} of the run)" if share is not None else ""
        if not row["plays"]:
            out.append(f"uplink MCS {lo}-{hi}{when}: no plays")
            continue
        top = ", ".join(f"{s} {f:.0%}" for s, f in list(row["share"].items())[:3])
        payload = row["mean_payload_bytes"]
        sent = f"; mean payload {payload / 1000:.1f} kB" if payload is not None else ""
        out.append(f"uplink MCS {lo}-{hi}{when}: {row['plays']} plays, {top}{sent}")
    return out


#: How far before and after a handover `around` looks, seconds: a few learner windows at
#: 20 Hz, and about the distance over which the cell edge's SINR falls at urban speeds.
AROUND_S = 3.0


@dataclass(frozen=True)
class Series:
    """What `around` looks at, on one clock (seconds since the run's start): the plays (when
    each was sent, its split, its request's latency, inf or NaN when lost), the mean payload
    of each split, EdgeLoc's error per frame, and the uplink MCS per channel step."""

    sent_s: Sequence[float]
    splits: Sequence[str]
    latency_s: Sequence[float]
    payload_bytes: Mapping[str, float]
    frame_t: Sequence[float]
    frame_error_m: Sequence[float]
    mcs_t: Sequence[float]
    ul_mcs: Sequence[int]

    def window(self, lo: float, hi: float) -> dict[str, Any]:
        """The figures of [lo, hi) (see `around`)."""
        chosen = [i for i, t in enumerate(self.sent_s) if lo <= t < hi]
        count = Counter(self.splits[i] for i in chosen)
        top, n = count.most_common(1)[0] if count else (None, 0)
        payload = self.payload_bytes
        sent = [payload[self.splits[i]] for i in chosen if self.splits[i] in payload]
        lat = [self.latency_s[i] for i in chosen if math.isfinite(self.latency_s[i])]
        err = [e for t, e in zip(self.frame_t, self.frame_error_m, strict=True) if lo <= t < hi]
        mcs = [m for t, m in zip(self.mcs_t, self.ul_mcs, strict=True) if lo <= t < hi]
        return {
            "plays": len(chosen),
            "top_split": top,
            "top_share": n / len(chosen) if chosen else None,
            "mean_payload_bytes": sum(sent) / len(sent) if sent else None,
            "mean_latency_s": sum(lat) / len(lat) if lat else None,
            "mean_error_m": sum(err) / len(err) if err else None,
            "mean_ul_mcs": sum(mcs) / len(mcs) if mcs else None,
        }


def around(at_s: float, series: Series, window_s: float = AROUND_S) -> dict[str, Any]:
    """The learner, EdgeLoc and the uplink in [at - window, at) ("before") and [at, at +
    window) ("after"): plays, the most played split and its share, mean payload and request
    latency, EdgeLoc's mean error over the frames, the mean uplink MCS over the channel's
    steps."""
    return {
        "before": series.window(at_s - window_s, at_s),
        "after": series.window(at_s, at_s + window_s),
    }


def around_lines(handovers: Sequence[Mapping[str, Any]]) -> list[str]:
    """What `testbed replay` prints per handover (`around` under "around")."""

    def side(w: Mapping[str, Any]) -> str:
        if not w["plays"]:
            return "no plays"
        payload = w["mean_payload_bytes"]
        sent = f", {payload / 1000:.1f} kB" if payload is not None else ""
        err = w["mean_error_m"]
        error = f", EdgeLoc {err:.2f} m" if err is not None else ""
        mcs = w["mean_ul_mcs"]
        ul = f"UL MCS {mcs:.0f}, " if mcs is not None else ""
        return f"{ul}{w['top_split']} {w['top_share']:.0%}{sent}{error}"

    return [
        f"{h['t_s']:.2f} s {h['source']} -> {h['target']}: before {side(h['around']['before'])};"
        f" after {side(h['around']['after'])}"
        for h in handovers
    ]
