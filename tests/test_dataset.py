"""The Dataset interface: synthetic drives and recorded folders read back exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodes.edgeloc.dataset import (
    Dataset,
    DatasetError,
    RecordedDataset,
    SyntheticDataset,
    export,
)
from nodes.edgeloc.model import IMAGE_SHAPE


@pytest.fixture(scope="module")
def short() -> SyntheticDataset:
    return SyntheticDataset(seed=3, rate_hz=20.0, duration_s=3.0)


def test_synthetic_dataset_is_a_dataset(short: SyntheticDataset) -> None:
    assert isinstance(short, Dataset)
    assert len(short) == 60 and short.rate_hz == 20.0
    assert short.timestamp(59) == pytest.approx(2.95)
    assert short.image(0).shape == short.image_shape == IMAGE_SHAPE  # the DNN's camera
    assert short.gt_pose(0).shape == (3,) and np.array_equal(short.vo_pose(0), short.gt_pose(0))
    with pytest.raises(IndexError, match="60 frames"):
        short.image(60)


def test_same_seed_same_frames_any_order(short: SyntheticDataset) -> None:
    again = SyntheticDataset(seed=3, rate_hz=20.0, duration_s=3.0)
    assert np.array_equal(again.image(40), short.image(40))  # frame 40 first, then 0
    assert np.array_equal(again.image(0), short.image(0))
    assert np.array_equal(again.vo_poses, short.vo_poses)
    other = SyntheticDataset(seed=4, rate_hz=20.0, duration_s=3.0)
    assert not np.array_equal(other.image(0), short.image(0))
    assert not np.allclose(other.gt_poses, short.gt_poses)


def test_rate_sets_the_frame_count() -> None:
    ds = SyntheticDataset(seed=3, rate_hz=10.0, duration_s=3.0)
    assert len(ds) == 30 and np.allclose(np.diff(ds.timestamps), 0.1)


def test_corruption_knob_is_off_by_default_and_degrades_frames() -> None:
    clean = SyntheticDataset(seed=5, duration_s=2.0)
    dirty = SyntheticDataset(seed=5, duration_s=2.0, corruption=1.0)
    assert clean.corruption == 0.0
    a, b = clean.image(3).astype(int), dirty.image(3).astype(int)
    assert np.abs(a - b).mean() > 10
    with pytest.raises(DatasetError, match="corruption"):
        SyntheticDataset(seed=5, corruption=2.0)


@pytest.mark.parametrize("fmt", ["npz", "png"])
def test_recorded_round_trip(tmp_path: Path, short: SyntheticDataset, fmt: str) -> None:
    folder = export(short, tmp_path / "rec", images=fmt)
    rec = RecordedDataset(folder)
    assert isinstance(rec, Dataset)
    assert len(rec) == len(short) and rec.rate_hz == pytest.approx(20.0)
    assert rec.image_shape == short.image_shape
    assert np.allclose(rec.timestamps, short.timestamps, atol=1e-6)
    assert np.allclose(rec.gt_poses, short.gt_poses, atol=1e-5)
    assert np.allclose(rec.vo_poses, short.vo_poses, atol=1e-5)
    for i in (0, 17, len(short) - 1):
        assert np.array_equal(rec.image(i), short.image(i))


def test_recorded_rate_from_timestamps_without_meta(tmp_path: Path, short: SyntheticDataset):
    folder = export(short, tmp_path / "rec")
    (folder / "meta.json").unlink()
    assert RecordedDataset(folder).rate_hz == pytest.approx(20.0, rel=1e-3)


def test_recorded_errors_say_what_is_wrong(tmp_path: Path, short: SyntheticDataset) -> None:
    with pytest.raises(DatasetError, match="does not exist"):
        RecordedDataset(tmp_path / "nowhere")
    folder = export(short, tmp_path / "rec")
    gt = (folder / "poses_gt.tum").read_text().splitlines()
    (folder / "vo.tum").write_text("\n".join(gt[:-3]) + "\n")
    with pytest.raises(DatasetError, match="same timestamps"):
        RecordedDataset(folder)
    (folder / "vo.tum").write_text("0.0 1 2 3\n")
    with pytest.raises(DatasetError, match=r"vo.tum:1: expected 8 values"):
        RecordedDataset(folder)
    (folder / "vo.tum").write_text("\n".join(gt) + "\n")
    (folder / "images.npz").unlink()
    with pytest.raises(DatasetError, match=r"neither images\.npz nor an images/ folder"):
        RecordedDataset(folder)
