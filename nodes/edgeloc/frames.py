"""A synthetic drive's camera frames rendered once, ahead, into one file every sensor reads.

Rendering a synthetic frame (`world.Camera.render`) costs more CPU than the vehicle's own
work on it: with eight vehicles each sensor drawing its own frames at 20 Hz, `sudo
.venv/bin/python tests/bench/bench_vehicles.py --seconds 30` printed 0.209 cores per vehicle,
against 0.133 with the frames rendered ahead (modes `before` and `apart`), and the emulation,
not the vehicles, set the latency. A real camera hands its frames over for nothing, so a run
renders the drive's frames before its nodes start, spread over the host's cores, into an `.npy`
array (N, H, W, 3) uint8 beside a JSON of what drive it holds (`FramesKey`); each sensor maps
the file read-only, so all of a run's vehicles (they drive the same seeded drive) share one
copy in the page cache. A frame beyond the file's end is rendered on demand, as before.

The frames depend only on the drive and the code that draws it, so `cached_frames` keeps them
from one run to the next (beside the DNN answers, `nodes.edgeloc.answerstore.cache_dir()`,
under `frames/`, keyed by the drive, the count, this package's sources and numpy's version;
the `CACHED_FILES` most recently used are kept): a second run of the same drive renders none.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import subprocess
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from nodes.edgeloc.dataset import U8, SyntheticDataset
from nodes.edgeloc.errors import EdgeLocError


class FramesError(EdgeLocError, ValueError):
    """A frames file that is not the drive the reader asked for."""


@dataclass(frozen=True)
class FramesKey:
    """Which synthetic drive a frames file holds."""

    seed: int
    rate_hz: float
    duration_s: float
    corruption: float = 0.0

    def dataset(self) -> SyntheticDataset:
        return SyntheticDataset(
            self.seed, self.rate_hz, self.duration_s, corruption=self.corruption
        )


def _key_path(path: Path) -> Path:
    return path.with_suffix(".json")


def _render_part(key: FramesKey, path: Path, part: int, parts: int) -> None:
    """A worker: render every `parts`-th frame from `part` into the shared file."""
    ds = key.dataset()
    out = np.load(path, mmap_mode="r+")
    for i in range(part, out.shape[0], parts):
        out[i] = ds.image(i)
    out.flush()


def render_frames(key: FramesKey, frames: int, path: Path, workers: int | None = None) -> Path:
    """Render the drive's first `frames` frames into `path` (.npy) and its key beside it, on
    `workers` processes (default: every CPU). Returns `path`."""
    ds = key.dataset()
    n = min(frames, len(ds))
    path.parent.mkdir(parents=True, exist_ok=True)
    out = np.lib.format.open_memmap(path, mode="w+", dtype=np.uint8, shape=(n, *ds.image_shape))
    del out  # the header is written; workers fill the frames through their own maps
    parts = max(1, min(workers or os.cpu_count() or 1, n))
    # Workers are fresh interpreters (`python -m nodes.edgeloc.frames`), neither forked (the
    # caller, a run, has threads, whose locks a fork would copy) nor multiprocessing's spawn
    # (which re-imports the caller's main script, and a script without a main guard would
    # run again in every worker).
    key_json = json.dumps(asdict(key))
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", __name__, key_json, str(path), str(p), str(parts)],
            stderr=subprocess.PIPE,
            text=True,
        )
        for p in range(parts)
    ]
    failed = []
    for p, proc in enumerate(procs):
        _, err = proc.communicate()
        if proc.returncode != 0:
            failed.append(f"part {p}: exit {proc.returncode}: {err.strip()[-500:]}")
    if failed:
        raise FramesError(f"rendering the frames into {path} failed: {'; '.join(failed)}")
    _key_path(path).write_text(key_json)
    return path


#: Frames files kept in the cache (~70 MB each for a 90-s drive at 20 Hz).
CACHED_FILES = 4


def cached_frames(key: FramesKey, frames: int) -> Path | None:
    """The drive's first `frames` frames from the cache, rendered into it first where no
    earlier run left them; None where the cache cannot be written (render into the run)."""
    from nodes.edgeloc.answerstore import cache_dir, hash_sources

    h = hashlib.sha256(json.dumps([asdict(key), frames, np.__version__]).encode())
    hash_sources(h)
    folder = cache_dir() / "frames"
    path = folder / f"{h.hexdigest()[:32]}.npy"
    if path.is_file() and _key_path(path).is_file():
        with contextlib.suppress(OSError):
            os.utime(path)  # recently used: kept when older files are pruned
        return path
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp = folder / f".{path.stem}.{os.getpid()}.npy"
        render_frames(key, frames, tmp)
        # the key first: a reader takes the frames once both are there
        os.replace(_key_path(tmp), _key_path(path))
        os.replace(tmp, path)
    except OSError:
        return None
    kept = sorted(folder.glob("*.npy"), key=lambda f: f.stat().st_mtime, reverse=True)
    for old in kept[CACHED_FILES:]:
        for f in (old, _key_path(old)):
            with contextlib.suppress(OSError):
                f.unlink()
    return path


class Frames:
    """A frames file opened read-only for one drive: `image(i)` from the file where it holds
    frame i, else rendered as `SyntheticDataset.image` would."""

    def __init__(self, path: Path, dataset: SyntheticDataset, key: FramesKey) -> None:
        try:
            written = FramesKey(**json.loads(_key_path(path).read_text()))
        except (OSError, ValueError, TypeError) as err:
            raise FramesError(f"frames file {path}: no readable key: {err}") from err
        if written != key:  # the duration too: a drive's route is generated for its length
            raise FramesError(f"frames file {path} holds drive {written}, not {key}")
        self._frames = np.load(path, mmap_mode="r")
        if self._frames.shape[1:] != dataset.image_shape:
            raise FramesError(
                f"frames file {path}: images {self._frames.shape[1:]}, "
                f"the camera's are {dataset.image_shape}"
            )
        self.dataset = dataset
        self.rendered_here = 0  # frames past the file's end, rendered on demand

    def __len__(self) -> int:
        return int(self._frames.shape[0])

    def image(self, i: int) -> U8:
        if 0 <= i < self._frames.shape[0]:
            return np.asarray(self._frames[i])
        self.rendered_here += 1
        return self.dataset.image(i)


if __name__ == "__main__":
    # A worker of `render_frames`: KEY_JSON PATH PART PARTS.
    _render_part(FramesKey(**json.loads(sys.argv[1])), Path(sys.argv[2]), *map(int, sys.argv[3:5]))
