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


def test_a_drives_frames_are_rendered_once_into_the_cache_and_read_from_it_after(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import nodes.edgeloc.frames as frames_module
    from nodes.edgeloc.frames import cached_frames

    monkeypatch.setenv("EDGELOC_CACHE_DIR", str(tmp_path))
    key = FramesKey(seed=5, rate_hz=20.0, duration_s=30.0)
    path = cached_frames(key, 6)
    assert path is not None and path.parent == tmp_path / "frames"
    ds = key.dataset()
    assert all(np.array_equal(Frames(path, ds, key).image(i), ds.image(i)) for i in range(6))

    def no_render(*_: object, **__: object) -> Path:
        raise AssertionError("rendered again although the cache holds the drive")

    monkeypatch.setattr(frames_module, "render_frames", no_render)
    assert cached_frames(key, 6) == path  # the second run of the drive renders nothing
    monkeypatch.undo()
    monkeypatch.setenv("EDGELOC_CACHE_DIR", str(tmp_path))
    others = [cached_frames(FramesKey(seed=s, rate_hz=20.0, duration_s=30.0), 2) for s in range(6)]
    assert path not in others and len(set(others)) == 6
    kept = sorted(p.name for p in (tmp_path / "frames").glob("*.npy"))
    assert len(kept) == frames_module.CACHED_FILES  # the least recently used went
