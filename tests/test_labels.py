"""Point labels that cover neither each other nor a marker (`reports.labels`), and the
error-against-latency figure that uses them: splits with close latencies and errors used to
stack their names into one unreadable smudge."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import pytest

from reports import plots
from reports.labels import covers, overlaps, place

FRAME = (0.0, 0.0, 800.0, 500.0)


def _marker(x: float, y: float, radius: float = 4.2) -> tuple[float, float, float]:
    return (x, y, radius)


def test_a_cluster_of_points_gets_labels_that_overlap_nothing() -> None:
    # 14 points within 6 px of each other, as seven splits of two phases crowd in a report.
    anchors = [(400 + 3 * (i % 3), 250 + 2 * (i % 4)) for i in range(14)]
    sizes = [(28.0 + 2 * i, 9.0) for i in range(14)]
    markers = [_marker(x, y) for x, y in anchors]
    boxes = place(anchors, sizes, markers, FRAME)
    assert len(boxes) == len(anchors)
    for a, b in itertools.combinations(boxes, 2):
        assert not overlaps(a, b), (a, b)
    for box, marker in itertools.product(boxes, markers):
        assert not covers(box, marker), (box, marker)
    for box, (w, h) in zip(boxes, sizes, strict=True):
        assert box[2] - box[0] == pytest.approx(w) and box[3] - box[1] == pytest.approx(h)
        assert FRAME[0] <= box[0] and box[2] <= FRAME[2] and FRAME[1] <= box[1]
        assert box[3] <= FRAME[3]


def test_a_lone_point_keeps_its_label_beside_it_up_and_right() -> None:
    (box,) = place([(100.0, 100.0)], [(30.0, 9.0)], [_marker(100, 100)], FRAME)
    assert box[0] > 100 and box[1] > 100  # right of and above the point
    assert box[0] - 100 <= 5 and box[1] - 100 <= 5  # and close to it


def test_a_point_at_the_frame_edge_gets_its_label_inside() -> None:
    (box,) = place([(795.0, 495.0)], [(30.0, 9.0)], [], FRAME)
    assert box[2] <= 800 and box[3] <= 500


def test_a_frame_too_small_for_any_label_still_keeps_labels_apart() -> None:
    # No spot fits inside: the frame is given up, not the spacing (the first goes right-up).
    boxes = place([(5.0, 5.0)] * 3, [(30.0, 9.0)] * 3, [], (0.0, 0.0, 10.0, 10.0))
    assert boxes[0] == (8.0, 8.0, 38.0, 17.0)
    for a, b in itertools.combinations(boxes, 2):
        assert not overlaps(a, b), (a, b)


def _crowded_summary() -> dict[str, Any]:
    splits = ["image", "conv1", "conv2", "conv3", "conv4", "fc", "vehicle"]
    rows = [
        {
            "policy": f"fixed:{s}",
            "phases": [
                {"mean_latency_s": 0.050 + 0.0004 * k + 0.001 * j, "mean_error_m": 0.80 + 0.003 * k}
                for j in range(2)
            ],
        }
        for k, s in enumerate(splits)
    ]
    rows += [
        {"policy": p, "phases": [{"mean_latency_s": 0.0515, "mean_error_m": 0.805}] * 2}
        for p in ("learned", "oracle")
    ]
    phases = [{"start_s": 0, "end_s": 10}, {"start_s": 10, "end_s": 20}]
    return {"splits": {"rows": rows, "phases": phases}}


def test_the_error_latency_figure_names_crowded_splits_without_overlap(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    saved: list[Any] = []
    real_save = plots._save

    def keep(fig: Any, folder: Path, name: str) -> str:
        saved.append(fig)
        return real_save(fig, folder, name)

    monkeypatch.setattr(plots, "_save", keep)
    assert plots.split_error_latency(_crowded_summary(), tmp_path) is not None
    (fig,) = saved
    (ax,) = fig.axes
    renderer = fig.canvas.get_renderer()
    names = [t for t in ax.texts if t.get_text() in {"image", "conv1", "conv4", "fc", "vehicle"}]
    assert len(names) == 10  # five of the splits, two phases each
    boxes = [t.get_window_extent(renderer) for t in ax.texts]
    assert len(boxes) == 14
    for a, b in itertools.combinations(boxes, 2):
        assert not a.overlaps(b), (a, b)
    inside = ax.get_window_extent(renderer)
    assert all(inside.x0 <= b.x0 and b.x1 <= inside.x1 for b in boxes)
    assert all(inside.y0 <= b.y0 and b.y1 <= inside.y1 for b in boxes)
