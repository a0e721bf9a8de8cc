"""The link self-test's table, from `linktest.json` as recorded: the one set of columns and
cell formats that `testbed link-test`, `testbed run` and the report all print."""

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
