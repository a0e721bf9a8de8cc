"""One CDF figure per case: for each measure, our delays beside the source's (its samples where
it gave them, else its published percentiles as points), one line per variant."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from testbed.fidelity.data import load_samples
from testbed.fidelity.judge import CaseResult

_AT = {"min": 0.0, "p50": 0.5, "p90": 0.9, "p95": 0.95, "p99": 0.99}


def cdf_figure(result: CaseResult, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    measures = list(result.case.probe.measures)
    fig, axes = plt.subplots(1, len(measures), figsize=(4.6 * len(measures), 3.6), squeeze=False)
    variants = {v.name: v for v in result.case.variants}
    for ax, measure in zip(axes[0], measures, strict=True):
        for i, judged in enumerate(result.variants):
            colour = f"C{i}"
            ms = np.sort(judged.samples.get(measure, []))
            if len(ms):
                ax.plot(
                    ms, np.arange(1, len(ms) + 1) / len(ms), colour, label=f"ours {judged.variant}"
                )
            variant = variants[judged.variant]
            if measure in variant.data:
                values, weights = load_samples(variant.data[measure])
                w = np.ones(len(values)) if weights is None else np.asarray(weights)
                order = np.argsort(values)
                v = np.asarray(values)[order]
                ax.plot(
                    v,
                    np.cumsum(w[order]) / w.sum(),
                    colour,
                    ls="--",
                    label=f"theirs {judged.variant}",
                )
            published = variant.published.get(measure, {})
            for name, value in published.items():
                if name in _AT:
                    ax.plot([value], [_AT[name]], colour, marker="o", ls="none")
                elif name == "mean":
                    ax.axvline(value, color=colour, ls=":", lw=1)
        ax.set_title(f"{result.case.name}: {measure}")
        ax.set_xlabel("delay (ms)")
        ax.set_ylabel("CDF")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.text(0.01, 0.01, "lines: ours; dashed: theirs; dots: their percentiles; dotted: their mean",
             fontsize=7)  # fmt: skip
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
    return path
