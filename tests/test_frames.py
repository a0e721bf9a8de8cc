"""The drive's camera frames rendered once, ahead, for every sensor (`nodes.edgeloc.frames`):
the file holds exactly the frames the sensor would render, a frame past its end is rendered on
demand, and a file of another drive is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodes.edgeloc.frames import Frames, FramesError, FramesKey, render_frames


def test_frames_rendered_ahead_are_the_frames_the_sensor_would_render(tmp_path: Path) -> None:
    key = FramesKey(seed=5, rate_hz=20.0, duration_s=30.0, corruption=0.2)
    path = render_frames(key, 12, tmp_path / "frames.npy", workers=2)
    ds = key.dataset()
    frames = Frames(path, ds, key)
    assert len(frames) == 12
    for i in (0, 1, 7, 11):  # both workers' frames
        assert np.array_equal(frames.image(i), ds.image(i)), i
    assert frames.rendered_here == 0
    assert np.array_equal(frames.image(12), ds.image(12))  # past the end: rendered here
    assert frames.rendered_here == 1


def test_a_frames_file_of_another_drive_is_refused(tmp_path: Path) -> None:
    key = FramesKey(seed=5, rate_hz=20.0, duration_s=30.0)
    path = render_frames(key, 2, tmp_path / "frames.npy", workers=1)
    other = FramesKey(seed=6, rate_hz=20.0, duration_s=30.0)
    with pytest.raises(FramesError, match="holds drive"):
        Frames(path, other.dataset(), other)
    path.with_suffix(".json").unlink()
    with pytest.raises(FramesError, match="no readable key"):
        Frames(path, key.dataset(), key)
