"""The link self-test's table, from `linktest.json` as recorded: the one set of columns and
cell formats that `testbed link-test`, `testbed run` and the report all print; and, for a
radio link, its lines beside the oracle (delay CDF points, HARQ shares, per-slot goodput)."""

from __future__ import annotations

from typing import Any

HEADERS = (
    "link",
    "dir",
    "rtt ms med/p99",
    "base ms",
    "owd ms med/p99",
    "sd ms",
    "tcp Mbit/s",
    "udp Mbit/s",
    "loss %",
    "ok",
    "checks",
)


def _fmt(value: Any, spec: str) -> str:
    return "-" if value is None else spec.format(value)


def _checks(verdicts: list[dict[str, Any]]) -> str:
    return "; ".join(
        f"{v.get('what')} {_fmt(v.get('measured'), '{:.3g}')} vs "
        f"{_fmt(v.get('expected'), '{:.3g}')} ({v.get('tolerance')})"
        + ("" if v.get("ok") else " OUT")
        for v in verdicts
    )


def rows(linktest: dict[str, Any]) -> list[list[str]]:
    """One row per link direction of a `linktest.json` dict: figures, then each verdict."""
    out = []
    for link in linktest.get("links", []):
        rtt = (
            f"{_fmt(link.get('rtt_median_ms'), '{:.2f}')}/{_fmt(link.get('rtt_p99_ms'), '{:.2f}')}"
        )
        for d in link.get("directions", []):
            out.append(
                [
                    str(link.get("link")),
                    str(d.get("direction")),
                    rtt,
                    _fmt(d.get("baseline_ms"), "{:.3f}"),
                    f"{_fmt(d.get('owd_median_ms'), '{:.3f}')}/"
                    f"{_fmt(d.get('owd_p99_ms'), '{:.2f}')}",
                    _fmt(d.get("jitter_sd_ms"), "{:.2f}"),
                    _fmt(d.get("tcp_mbit"), "{:.2f}"),
                    _fmt(d.get("udp_mbit"), "{:.2f}"),
                    f"{_fmt(d.get('loss_pct'), '{:.2f}')} of {d.get('loss_packets', '-')}",
                    "ok" if d.get("ok") else "OUT",
                    _checks(d.get("verdicts", [])),
                ]
            )
    return out


def text(linktest: dict[str, Any]) -> str:
    """The table as aligned plain text (what the CLI prints)."""
    body = rows(linktest)
    widths = [len(h) for h in HEADERS]
    for row in body:
        widths = [max(w, len(c)) for w, c in zip(widths, row, strict=True)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(HEADERS, widths, strict=True))]
    lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)) for row in body]
    return "\n".join(line.rstrip() for line in lines)


#: The CDF points the text shows of a radio direction's delays (of those linktest.json keeps).
SHOWN_QUANTILES = (0.1, 0.25, 0.5, 0.75, 0.9, 0.99)


def radio_directions(linktest: dict[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    """(link, direction, radio figures) of every direction with a radio."""
    return [
        (str(link.get("link")), str(d.get("direction")), d["radio"])
        for link in linktest.get("links", [])
        for d in link.get("directions", [])
        if isinstance(d.get("radio"), dict)
    ]


def cdf_points(radio: dict[str, Any]) -> list[tuple[float, float, float]]:
    """(probability, measured ms, oracle ms) at SHOWN_QUANTILES, from what was kept."""
    at = {round(q, 9): i for i, q in enumerate(radio.get("quantiles") or [])}
    return [
        (q, radio["measured_ms"][at[q]], radio["oracle_ms"][at[q]])
        for q in SHOWN_QUANTILES
        if q in at
    ]


def harq_text(harq: dict[str, Any]) -> str:
    """`blocks 1200: +0 89.9% (90), +1 9.1% (9), ..., lost 0% (0.001)`: measured (expected)."""
    shares, expected = harq.get("shares", []), harq.get("expected", [])
    parts = []
    for k, (got, want) in enumerate(zip(shares, expected, strict=False)):
        label = "lost" if k == len(shares) - 1 else f"+{k}"
        parts.append(f"{label} {got * 100:.3g}% ({want * 100:.3g})")
    return f"blocks {harq.get('blocks', 0)}: " + ", ".join(parts)


def slots_text(slots: dict[str, Any]) -> str:
    """`4610 B per occasion (4619 expected: a 5132 B block less 10% resends), 5120 B per new
    block, 1080 occasions, 88% of those in 2.05 s`."""
    share = slots.get("used_share")
    return (
        f"{_fmt(slots.get('bytes_per_occasion'), '{:.0f}')} B per occasion "
        f"({_fmt(slots.get('expected_bytes_per_occasion'), '{:.0f}')} expected: a "
        f"{_fmt(slots.get('block_bytes'), '{:.0f}')} B block less the resends), "
        f"{_fmt(slots.get('bytes_per_block'), '{:.0f}')} B per new block, "
        f"{slots.get('occasions', 0)} occasions at saturation"
        + (
            f", {share * 100:.0f}% of the {_fmt(slots.get('occasions_per_s'), '{:.0f}')}/s "
            f"in {slots.get('seconds', 0):.2f} s"
            if isinstance(share, (int, float))
            else ""
        )
    )


def radio_lines(linktest: dict[str, Any]) -> list[str]:
    """Per radio direction: the distance from the oracle and its tolerance, measured and
    oracle delays at a few CDF points, HARQ shares and the per-slot goodput."""
    out: list[str] = []
    floor = linktest.get("timer_floor")
    for link, direction, radio in radio_directions(linktest):
        head = (
            f"radio {link} {direction}: W1 {_fmt(radio.get('w1_ms'), '{:.3f}')} ms, "
            f"KS {_fmt(radio.get('ks'), '{:.3f}')} from the oracle over "
            f"{radio.get('samples', 0)} probes (tolerance "
            f"{_fmt(radio.get('tolerance_ms'), '{:.3g}')} ms"
        )
        if "sampling_tolerance_ms" in radio:
            head += (
                f" = host {_fmt(radio.get('host_tolerance_ms'), '{:.3g}')} + "
                f"{_fmt(radio.get('sampling_tolerance_ms'), '{:.3g}')} for "
                f"{radio.get('samples', 0)} probes by chance"
            )
        if isinstance(floor, dict):
            head += f"; timer floor p99 {_fmt(floor.get('p99_ms'), '{:.3f}')} ms"
        out.append(head + ")")
        points = cdf_points(radio)
        if points:
            out.append("  cdf        " + "  ".join(f"p{round(q * 100):<5d}" for q, _, _ in points))
            out.append("  measured   " + "  ".join(f"{m:<6.2f}" for _, m, _ in points) + "ms")
            out.append("  oracle     " + "  ".join(f"{o:<6.2f}" for _, _, o in points) + "ms")
        if isinstance(radio.get("harq"), dict):
            out.append("  HARQ       " + harq_text(radio["harq"]))
        if isinstance(radio.get("slots"), dict):
            out.append("  per slot   " + slots_text(radio["slots"]))
    return [line.rstrip() for line in out]
