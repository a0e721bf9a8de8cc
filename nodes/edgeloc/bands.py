"""The split learner's choices grouped by the radio each request met.

With a scenario `channel:` the uplink's MCS follows the vehicle's place, not the clock, so
"phases between timeline events" no longer say what the network was. Instead each play is put
in the band of the uplink MCS at the instant its request was sent, and per band the report
says how the learner chose: plays, the share of each split, and the mean payload it sent (a
learner that follows the radio sends less where the MCS is low). Pure: numbers in, a table out;
`testbed.replay` and `reports.summary` both use it.
"""

from __future__ import annotations

import bisect
from collections import Counter
from collections.abc import Mapping, Sequence
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
