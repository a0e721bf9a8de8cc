"""The DNN's answers to a drive's frames, kept on disk from one report to the next.

A report replays the run's drive once per fixed split (`compare.compare_splits`), and every
replay asks the split DNN for each frame it plays: a synthetic frame rendered, the head, the
codec and the tail, ~10 ms per frame and split. The answers depend on nothing the run measured:
only on the drive (the synthetic world regenerated from the config's seed, rate, duration and
corruption), the weights, the codec and the code that computes them. So they are stored under
a key made of exactly those — the weights' tensors, the drive's parameters, the codec, the
sources of this package and the versions of torch and numpy — and the next report of the same
drive (`make scenario` run again, a sweep's variants, `testbed report` of a run) reads them
instead of computing them. Any change to one of those parts is another key: a stale answer
cannot be read. The answers read are the ones the DNN would give, so a report is the same with
or without the store (tests/test_answerstore.py checks it).

Where: `$EDGELOC_CACHE_DIR`, else `$XDG_CACHE_HOME/edgeloc-testbed`, else
`~/.cache/edgeloc-testbed`; under `answers/`, one `.npz` per key (about 24 bytes an answer),
the least recently used removed beyond `MAX_FILES`. `make clean` removes the folder. A store
that cannot be read or written is skipped, never an error: it only saves time.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from nodes.edgeloc.model import LocNet
    from nodes.edgeloc.replay import Answer

CACHE_ENV = "EDGELOC_CACHE_DIR"
#: Stores kept (one per drive, weights and codec); the oldest read goes first.
MAX_FILES = 32
_PACKAGE = Path(__file__).resolve().parent


def cache_dir() -> Path:
    """The folder of the testbed's caches (see the module doc)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "edgeloc-testbed"


def hash_sources(h: Any) -> None:
    """Feed this package's sources to the hash `h`: what a kept answer or frame was computed
    by (any edit makes another key)."""
    for source in sorted(_PACKAGE.glob("*.py")):
        h.update(source.name.encode())
        h.update(source.read_bytes())


def answers_key(model: LocNet, drive: Mapping[str, Any], codec: str) -> str:
    """The key of the answers `model` gives to `drive`'s frames through `codec`."""
    import torch

    h = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        h.update(name.encode())
        h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    hash_sources(h)
    parts = {"drive": dict(drive), "codec": codec, "torch": torch.__version__,
             "numpy": np.__version__}  # fmt: skip
    h.update(json.dumps(parts, sort_keys=True, default=str).encode())
    return h.hexdigest()[:32]


class AnswerStore:
    """The stored answers of one key: `load` what is there, `save` what is known now."""

    def __init__(self, key: str, folder: Path | None = None) -> None:
        self.key = key
        self.path = (folder or cache_dir() / "answers") / f"{key}.npz"
        self.loaded = 0

    def load(self) -> dict[tuple[int, str], Answer]:
        """The answers stored under this key ({} when there are none or they do not read)."""
        from nodes.edgeloc.replay import Answer

        try:
            with np.load(self.path, allow_pickle=False) as z:
                frames, splits = z["frames"].tolist(), z["splits"].tolist()
                poses, payloads, entropy = z["poses"], z["payloads"].tolist(), z["entropy"]
            os.utime(self.path)  # recently used: kept when older stores are pruned
        except (OSError, KeyError, ValueError):
            return {}
        out = {}
        for i, (frame, split) in enumerate(zip(frames, splits, strict=True)):
            e = float(entropy[i])
            out[frame, split] = Answer(poses[i].copy(), payloads[i], None if math.isnan(e) else e)
        self.loaded = len(out)
        return out

    def save(self, answers: Mapping[tuple[int, str], Answer]) -> None:
        """Store `answers` (all of them: what was loaded and what is new), if any are new."""
        if len(answers) <= self.loaded:
            return
        keys = sorted(answers)
        rows = [answers[k] for k in keys]
        arrays = {
            "frames": np.array([f for f, _ in keys], dtype=np.int64),
            "splits": np.array([s for _, s in keys], dtype=np.str_),
            "poses": np.array([np.asarray(a.pose, dtype=np.float64) for a in rows]),
            "payloads": np.array([a.payload for a in rows], dtype=np.int64),
            "entropy": np.array(
                [math.nan if a.entropy_nats is None else a.entropy_nats for a in rows]
            ),
        }
        with contextlib.suppress(OSError):
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=self.path.parent, prefix=".answers-", suffix=".npz")
            try:
                with os.fdopen(fd, "wb") as f:
                    np.savez(f, **arrays)
                os.replace(tmp, self.path)  # a reader sees the old file or the new one
            except BaseException:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
                raise
            self.loaded = len(answers)
            _prune(self.path.parent)


def _prune(folder: Path) -> None:
    stores = sorted(folder.glob("*.npz"), key=lambda p: p.stat().st_mtime, reverse=True)
    for old in stores[MAX_FILES:]:
        with contextlib.suppress(OSError):
            old.unlink()
