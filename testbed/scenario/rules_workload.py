"""The rules of `workload:`: paths relative to the scenario file, and fields that go together.

The dataset folder and the weights file exist; the learner's fixed split is one of the
splits; the fusion's correlation, robust centre and confidence come only with the methods that
use them, and a confidence calibration lies beside the weights.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from testbed.scenario import model, schema_v1
from testbed.scenario.building import Builder
from testbed.scenario.issues import did_you_mean
from testbed.scenario.kinds import Section
from testbed.scenario.rules_topology import NAME_CUTOFF, listing


def build(b: Builder) -> model.Workload:
    """The `Workload`; the default one when anything so far is wrong (reported)."""
    workload: Section | str | None = b.root.get("workload")
    if workload is None:
        return model.Workload()
    if isinstance(workload, str):  # `workload: none` or `workload: edgeloc`
        return model.Workload(kind=workload)  # type: ignore[arg-type]
    changes: dict[str, Any] = {}
    dataset = workload.get("dataset")
    if workload.written("dataset") and dataset != "synthetic" and dataset is not None:
        folder = b.base_dir / dataset
        if folder.is_dir():
            changes["dataset"] = folder.resolve()
        else:
            b.ctx.add(
                workload.at("dataset"),
                workload.path_of("dataset"),
                "'synthetic' or an existing folder of recorded data (relative to the "
                "scenario file)",
                f"{dataset!r} ({'a file' if folder.exists() else 'no such folder'})",
            )
    weights = workload.get("weights")
    if weights is not None:
        file = b.base_dir / weights
        if file.is_file():
            changes["weights"] = file.resolve()
        else:
            b.ctx.add(
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
        b.ctx.add(
            learner.at("fixed_split"),
            learner.path_of("fixed_split"),
            f"one of the splits listed in workload.splits ({listing(list(splits))})",
            repr(fixed),
            did_you_mean(fixed, list(splits), NAME_CUTOFF),
        )
    fusion: Section | None = workload.get("fusion")
    if (
        isinstance(fusion, Section)
        and fusion.get("correlation") is not None
        and fusion.get("method", "paper") != "ekf"
    ):
        b.ctx.add(
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
            b.ctx.add(
                fusion.at("robust_centre"),
                fusion.path_of("robust_centre"),
                "robust_centre only with the paper's fusion and a robust weight (it centres"
                " that weight): method: paper and robust set, or no robust_centre",
                "robust: null" if no_robust else f"robust_centre with method {method!r}",
            )
    if isinstance(fusion, Section) and fusion.get("confidence"):
        method = fusion.get("method", "paper")
        if method != "paper":
            b.ctx.add(
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
                b.ctx.add(
                    fusion.at("confidence"),
                    fusion.path_of("confidence"),
                    "a confidence calibration beside the weights (`python -m"
                    " nodes.edgeloc.train --calibrate --out DIR` writes it)",
                    str(e),
                )
    if not workload.clean or b.ctx.issues:
        return model.Workload()
    built: model.Workload = schema_v1.WORKLOAD.build(workload)
    return dataclasses.replace(built, **changes)
