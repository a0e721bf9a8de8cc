"""The sensor stream every EdgeLoc node reads: one `Dataset` interface, two sources.

A dataset is a sequence of frames at a fixed rate; frame `i` has a timestamp, a camera image
(H x W x 3 uint8), the visual-odometry pose `L_beta` and the ground-truth pose `L_gt` (SE(2)
[x, y, yaw], see `geometry`). Downstream code (sensor node, DNN, reports) only sees `Dataset`.

- `SyntheticDataset` drives through the seeded synthetic town (`world`), rendering each image on
  demand, so a real-time node can ask for frame `i` at 20 Hz without holding a video in memory.
- `RecordedDataset` reads a folder exported from a real recording (KITTI, RobotCar) or by
  `export()`. Folder format:

      <folder>/
        poses_gt.tum     ground truth, TUM format: one line per frame
                         `timestamp tx ty tz qx qy qz qw` (seconds, metres, unit quaternion);
                         `#` comment lines are skipped. z is up: x, y is the ground plane and
                         yaw is the rotation about z (convert camera-frame poses, e.g. KITTI's
                         z-forward frame, to a z-up frame when exporting).
        vo.tum           visual odometry in the same format and frame, one line per frame with
                         the same timestamps as poses_gt.tum (within 1 ms).
        images.npz       array `images` of shape (N, H, W, 3), dtype uint8, frame order;
        or images/       `<index>.png` per frame (0.png, 1.png, ...; zero padding allowed),
                         RGB, all of one size (needs Pillow).
        meta.json        optional: {"rate_hz": 20.0}; otherwise the rate is 1 / median step.

  Timestamps are given relative to the first frame (`RecordedDataset.t0` keeps the original).

  The DNN must be trained on images of the same size and place as the recording.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from nodes.edgeloc.errors import EdgeLocError
from nodes.edgeloc.metrics import read_tum, write_tum
from nodes.edgeloc.world import (
    DEFAULT_TOWN_SEED,
    Camera,
    Drive,
    Town,
    VoNoise,
    vo_trace,
)

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]


class DatasetError(EdgeLocError, ValueError):
    """A dataset folder or argument that cannot be used; the message says what to fix."""


@runtime_checkable
class Dataset(Protocol):
    """Frames at a fixed rate: timestamp, image, VO pose and ground-truth pose per index."""

    @property
    def rate_hz(self) -> float: ...

    @property
    def image_shape(self) -> tuple[int, int, int]:
        """(H, W, 3) of every image."""
        ...

    @property
    def timestamps(self) -> F64:
        """(N,) seconds, increasing."""
        ...

    @property
    def vo_poses(self) -> F64:
        """(N, 3) VO poses `L_beta` [x, y, yaw]."""
        ...

    @property
    def gt_poses(self) -> F64:
        """(N, 3) ground-truth poses `L_gt` [x, y, yaw]."""
        ...

    def __len__(self) -> int: ...

    def timestamp(self, i: int) -> float: ...

    def image(self, i: int) -> U8: ...

    def vo_pose(self, i: int) -> F64: ...

    def gt_pose(self, i: int) -> F64: ...


class _PoseArrays:
    """Per-index accessors shared by both datasets, on top of the three arrays."""

    _t: F64
    _vo: F64
    _gt: F64

    @property
    def timestamps(self) -> F64:
        return self._t

    @property
    def vo_poses(self) -> F64:
        return self._vo

    @property
    def gt_poses(self) -> F64:
        return self._gt

    def __len__(self) -> int:
        return len(self._t)

    def _check(self, i: int) -> int:
        n = len(self._t)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range: the dataset has {n} frames")
        return i % n

    def timestamp(self, i: int) -> float:
        return float(self._t[self._check(i)])

    def vo_pose(self, i: int) -> F64:
        return self._vo[self._check(i)].copy()

    def gt_pose(self, i: int) -> F64:
        return self._gt[self._check(i)].copy()


class SyntheticDataset(_PoseArrays):
    """A drive through the synthetic town: route, lighting, trucks and VO noise from `seed`.

    The town itself comes from `town_seed` (default: the town the committed DNN was trained
    on), so every `seed` is a new drive through the same, known place, as in RobotCar.
    `corruption` in [0, 1] is an experiment knob, off by default: that fraction of frames gets
    a degraded image (heavy noise and washed-out contrast, like a wet or dirty lens).
    """

    def __init__(
        self,
        seed: int,
        rate_hz: float = 20.0,
        duration_s: float = 90.0,
        *,
        town_seed: int = DEFAULT_TOWN_SEED,
        width: int = 128,  # the camera the committed DNN expects (model.IMAGE_SHAPE)
        height: int = 96,
        corruption: float = 0.0,
        vo_noise: VoNoise | None = None,
    ) -> None:
        if rate_hz <= 0 or duration_s <= 0:
            raise DatasetError(f"rate_hz ({rate_hz}) and duration_s ({duration_s}) must be > 0")
        if not 0.0 <= corruption <= 1.0:
            raise DatasetError(f"corruption must be within [0, 1], got {corruption}")
        self.seed = seed
        self.corruption = corruption
        self.town = Town.generate(town_seed)
        self.drive = Drive.generate(self.town, seed, rate_hz, duration_s)
        self.camera = Camera(self.town, width=width, height=height)
        # the VO gets its own stream so the drive does not change when VO settings do
        vo_rng = np.random.default_rng([seed, 1])
        self._t = self.drive.t
        self._gt = self.drive.poses
        self._vo = vo_trace(self._gt, rate_hz, vo_rng, vo_noise or VoNoise())
        self._rate = float(rate_hz)

    @property
    def rate_hz(self) -> float:
        return self._rate

    @property
    def image_shape(self) -> tuple[int, int, int]:
        return (self.camera.height, self.camera.width, 3)

    def image(self, i: int) -> U8:
        i = self._check(i)
        rng = np.random.default_rng([self.seed, 2, i])  # per frame: any order gives the same
        img = self.camera.render(
            self._gt[i], self.drive.lighting(i), self.drive.obstacles(i), noise_rng=rng
        )
        if self.corruption > 0 and rng.random() < self.corruption:
            img = corrupt(img, rng)
        return img


def corrupt(img: U8, rng: np.random.Generator) -> U8:
    """A degraded camera frame: contrast washed towards grey plus strong noise."""
    x = img.astype(np.float64)
    x = 0.4 * x + 0.6 * 150.0 + rng.normal(0.0, 25.0, size=x.shape)
    return np.clip(x, 0, 255).astype(np.uint8)


# ---- recorded data ---------------------------------------------------------------------------


class _Tum:
    """A TUM trajectory as (stamps, SE(2) poses), read with `metrics.read_tum` (one TUM codec)."""

    def __init__(self, t: F64, poses: F64) -> None:
        self.t, self.poses = t, poses


def _read_tum(path: Path) -> _Tum:
    if not path.is_file():
        raise DatasetError(f"{path} is missing (TUM file: `timestamp tx ty tz qx qy qz qw`)")
    try:
        t, poses = read_tum(path)
    except ValueError as err:
        raise DatasetError(str(err)) from None
    if np.any(np.diff(t) <= 0):
        raise DatasetError(f"{path}: timestamps must increase strictly")
    return _Tum(t, poses)


class RecordedDataset(_PoseArrays):
    """Frames read from a folder (format in the module docstring)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise DatasetError(f"dataset folder {self.folder} does not exist")
        gt = _read_tum(self.folder / "poses_gt.tum")
        vo = _read_tum(self.folder / "vo.tum")
        if len(gt.t) != len(vo.t) or np.max(np.abs(gt.t - vo.t)) > 1e-3:
            raise DatasetError(
                f"{self.folder}: vo.tum ({len(vo.t)} poses) and poses_gt.tum ({len(gt.t)}) "
                "must have one line per frame with the same timestamps"
            )
        self._t, self._gt, self._vo = gt.t - gt.t[0] + 0.0, gt.poses, vo.poses
        self.t0 = float(gt.t[0])  # the recording's own clock at frame 0
        self._images: U8 | None = None
        self._pngs: list[Path] | None = None
        npz, pngdir = self.folder / "images.npz", self.folder / "images"
        if npz.is_file():
            with np.load(npz) as z:
                if "images" not in z:
                    raise DatasetError(f"{npz} has no array named `images`")
                self._images = z["images"]
            if self._images.dtype != np.uint8 or self._images.ndim != 4:
                raise DatasetError(f"{npz}: `images` must be (N, H, W, 3) uint8")
            shape = self._images.shape[1:]
            count = len(self._images)
        elif pngdir.is_dir():
            self._pngs = _numbered_pngs(pngdir)
            count = len(self._pngs)
            shape = self._load_png(0).shape if count else (0, 0, 3)
        else:
            raise DatasetError(f"{self.folder} has neither images.npz nor an images/ folder")
        if count != len(self._t):
            raise DatasetError(f"{self.folder}: {count} images for {len(self._t)} poses")
        if len(shape) != 3 or shape[2] != 3:
            raise DatasetError(f"{self.folder}: images must be RGB (H, W, 3), got {shape}")
        self._shape = (int(shape[0]), int(shape[1]), 3)
        self._rate = self._read_rate()

    def _read_rate(self) -> float:
        meta = self.folder / "meta.json"
        if meta.is_file():
            try:
                rate = float(json.loads(meta.read_text())["rate_hz"])
            except (ValueError, KeyError, TypeError) as e:
                raise DatasetError(f'{meta}: expected {{"rate_hz": <number>}} ({e})') from None
            if rate <= 0:
                raise DatasetError(f"{meta}: rate_hz must be > 0")
            return rate
        if len(self._t) < 2:
            raise DatasetError(f"{self.folder}: one frame has no rate; add meta.json")
        return float(1.0 / np.median(np.diff(self._t)))

    def _load_png(self, i: int) -> U8:
        try:
            from PIL import Image
        except ImportError:
            raise DatasetError("reading images/*.png needs Pillow: pip install pillow") from None
        assert self._pngs is not None
        with Image.open(self._pngs[i]) as im:
            return np.asarray(im.convert("RGB"), dtype=np.uint8)

    @property
    def rate_hz(self) -> float:
        return self._rate

    @property
    def image_shape(self) -> tuple[int, int, int]:
        return self._shape

    def image(self, i: int) -> U8:
        i = self._check(i)
        if self._images is not None:
            return self._images[i]
        img = self._load_png(i)
        if img.shape != self._shape:
            raise DatasetError(f"{self._pngs[i]}: size {img.shape} differs from {self._shape}")
        return img


def _numbered_pngs(folder: Path) -> list[Path]:
    found: dict[int, Path] = {}
    for p in folder.iterdir():
        m = re.fullmatch(r"(\d+)\.png", p.name)
        if m:
            found[int(m.group(1))] = p
    if sorted(found) != list(range(len(found))):
        raise DatasetError(f"{folder}: PNG files must be numbered 0.png .. N-1.png without gaps")
    return [found[i] for i in range(len(found))]


def export(dataset: Dataset, folder: str | Path, images: str = "npz") -> Path:
    """Write `dataset` in the recorded-folder format (`images`: "npz" or "png")."""
    if images not in ("npz", "png"):
        raise DatasetError(f"images must be 'npz' or 'png', got {images!r}")
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "poses_gt.tum", dataset.timestamps, dataset.gt_poses)
    write_tum(out / "vo.tum", dataset.timestamps, dataset.vo_poses)
    (out / "meta.json").write_text(json.dumps({"rate_hz": dataset.rate_hz}) + "\n")
    frames = [dataset.image(i) for i in range(len(dataset))]
    if images == "npz":
        np.savez_compressed(out / "images.npz", images=np.stack(frames))
    else:
        from PIL import Image

        (out / "images").mkdir(exist_ok=True)
        for i, f in enumerate(frames):
            Image.fromarray(f).save(out / "images" / f"{i}.png")
    return out


def open_dataset(
    source: str | Path,
    seed: int = 0,
    rate_hz: float = 20.0,
    duration_s: float = 90.0,
    corruption: float = 0.0,
) -> Dataset:
    """`"synthetic"` gives a `SyntheticDataset`; a folder path gives a `RecordedDataset`."""
    if str(source) == "synthetic":
        return SyntheticDataset(seed, rate_hz, duration_s, corruption=corruption)
    return RecordedDataset(source)
