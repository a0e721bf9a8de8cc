"""The localization DNN: a small PoseNet-style CNN that can be cut at named split points.

The paper regresses the vehicle's absolute pose from one camera image with an end-to-end DNN
(PoseNet) and splits it between the vehicle (layers [0:k]) and the RSU (layers [k:]). `LocNet`
is that network for a 128x96 camera: a stack of stages, and a split point between every two
stages. Each split point has a name and an activation of its own size:

    split     runs on the vehicle            sends to the edge (128x96 camera)
    image     nothing                        the raw uint8 frame (3x96x128 = 36864 values)
    conv1     2x2 mean (to 64x48), 5x5/2 conv 16x24x32 floats (12288: more than the 64x48
                                             network input, as PoseNet's first layers)
    conv2     + 3x3/2 conv                   32x12x16 (6144)
    conv3     + 3x3/2 conv                   48x6x8   (2304)
    conv4     + 3x3/2 conv                   64x3x4   (768)
    fc        + fully connected              256
    vehicle   everything                     the pose itself (4 values): nothing for the edge

Why the camera is larger than the network input: PoseNet resizes each camera frame to its input
size as the first step of inference; here the first stage averages 2x2 pixel blocks. The camera
frame is what the `image` split must send, and its size sets the uplink cost of offloading
everything: at 128x96 it is 36.9 kB, about what one compressed HD frame or one raw low-resolution
frame weighs, so the cost ordering of splits flips within the 8-40 Mbit/s of a loaded 5G uplink
(a 64x48 frame, 9.2 kB, made sending the image the cheapest choice down to ~2 Mbit/s).

`head(k, x)` runs stages [0:k] and `tail(k, a)` runs [k:], so `tail(k, head(k, x))` is exactly
`forward(x)`. The input is the camera image as uint8 (N, H, W, 3), so the `image` split sends
what the camera gave. The output is (N, 4): x and y in metres and yaw as a unit (cos, sin).
Position comes from place recognition over street anchors plus a regressed offset (`_PoseOut`).
`tail_with_entropy` also returns the entropy of that place classifier (`place_entropy`): the
DNN's own doubt, which rises with its error (`train.entropy_calibration`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from nodes.edgeloc.settings import SPLITS

# SPLITS (the split-point names) lives in the torch-free settings module; the layers below
# implement them in that order.
IMAGE_SHAPE = (96, 128, 3)  # H, W, C of the camera the committed weights expect
INPUT_POOL = 2  # the first stage averages INPUT_POOL x INPUT_POOL pixel blocks (PoseNet's resize)
DEFAULT_ROADS = tuple(-200.0 + 80.0 * i for i in range(6))  # road grid of the default town


def split_index(split: int | str) -> int:
    """The stage index of a split point given by name or index; a clear error otherwise."""
    if isinstance(split, str):
        if split not in SPLITS:
            raise ValueError(f"unknown split point {split!r}; known: {', '.join(SPLITS)}")
        return SPLITS.index(split)
    if not 0 <= int(split) < len(SPLITS):
        raise ValueError(f"split index {split} out of range 0..{len(SPLITS) - 1}")
    return int(split)


class _ToFloat(nn.Module):
    """uint8 (N, H, W, 3) camera image -> float (N, 3, H/p, W/p) centred on zero, where each
    output pixel is the mean of a p x p block (the resize to the network's input size)."""

    def __init__(self, pool: int = 1) -> None:
        super().__init__()
        self.pool = int(pool)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x.permute(0, 3, 1, 2).to(torch.float32) / 127.5 - 1.0
        return nn.functional.avg_pool2d(x, self.pool) if self.pool > 1 else x


class _PoseOut(nn.Module):
    """Last layer: place recognition over anchors, then a metric offset and the heading.

    Anchors are points every few metres along the town's streets. The layer scores each
    anchor (softmax logits), takes the best one, refines it to the probability-weighted mean
    of its neighbourhood plus a regressed offset (in units of `spacing`), and regresses yaw as
    (cos, sin). Classifying places trains far faster than
    regressing raw coordinates, and it fails like PoseNet does: on look-alike streets it picks
    the wrong place with confidence, which is an outlier, not a small error.
    """

    def __init__(self, features: int, anchors: torch.Tensor, spacing: float) -> None:
        super().__init__()
        self.register_buffer("anchors", anchors.to(torch.float32).reshape(-1, 2))
        self.register_buffer("spacing", torch.tensor(float(spacing)))
        self.linear = nn.Linear(features, len(self.anchors) + 4)
        # each anchor's neighbourhood (itself and the anchors next to it along the streets):
        # the place is the probability-weighted mean of the best anchor's neighbourhood
        d = torch.cdist(self.anchors, self.anchors)
        k = min(5, len(self.anchors))
        dist, idx = torch.topk(d, k, dim=1, largest=False)
        self.register_buffer("neighbours", idx, persistent=False)
        self.register_buffer("near", dist <= 1.5 * float(spacing), persistent=False)

    def parts(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Anchor logits (N, A), position (N, 2) in metres and unit (cos, sin) (N, 2)."""
        z = self.linear(x)
        a = len(self.anchors)
        logits = z[:, :a]
        best = logits.argmax(dim=1)
        nb = self.neighbours[best]  # (N, k)
        local = logits.gather(1, nb).masked_fill(~self.near[best], float("-inf"))
        w = torch.softmax(local, dim=1)
        xy = (w[..., None] * self.anchors[nb]).sum(dim=1) + z[:, a : a + 2] * self.spacing
        cs = nn.functional.normalize(z[:, a + 2 :], dim=1, eps=1e-6)
        return logits, xy, cs

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        _, xy, cs = self.parts(x)
        return torch.cat([xy, cs], dim=1)


def street_anchors(road_coords: Sequence[float], spacing: float, margin: float) -> torch.Tensor:
    """(A, 2) points every `spacing` metres along every road centreline of a square grid."""
    roads = np.asarray(road_coords, dtype=np.float64)
    along = np.arange(roads[0] - margin, roads[-1] + margin + 1e-9, spacing)
    on_x = np.stack(np.meshgrid(along, roads), -1).reshape(-1, 2)  # streets along x
    on_y = np.stack(np.meshgrid(roads, along), -1).reshape(-1, 2)  # streets along y
    pts = np.concatenate([on_x, on_y])
    return torch.from_numpy(np.unique(np.round(pts, 3), axis=0))


def _conv(cin: int, cout: int, k: int, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(cin, cout, k, stride, k // 2, bias=False), nn.BatchNorm2d(cout), nn.ReLU()]


class LocNet(nn.Module):
    """PoseNet-style CNN whose stages end at the named split points in `SPLITS`."""

    def __init__(
        self,
        image_shape: tuple[int, int, int] = IMAGE_SHAPE,
        anchors: torch.Tensor | None = None,
        spacing: float = 15.0,
        seed: int = 0,
        pool: int = INPUT_POOL,
    ) -> None:
        super().__init__()
        h, w, c = image_shape
        m = 16 * pool  # four stride-2 convolutions after the pooling
        if pool < 1 or c != 3 or h % m or w % m:
            raise ValueError(
                f"image shape must be (H, W, 3) with H, W multiples of {m} (pool {pool}): {h, w, c}"
            )
        self.image_shape = (h, w, c)
        self.pool = pool
        if anchors is None:  # the default town's streets (the committed weights' anchors)
            anchors = street_anchors(DEFAULT_ROADS, spacing, margin=spacing)
        with torch.random.fork_rng(devices=[]):  # deterministic init, global RNG untouched
            torch.manual_seed(seed)
            self.stages = nn.ModuleList(
                [
                    nn.Sequential(_ToFloat(pool), *_conv(3, 16, 5, stride=2)),  # -> conv1
                    nn.Sequential(*_conv(16, 32, 3, stride=2)),  # -> conv2
                    nn.Sequential(*_conv(32, 48, 3, stride=2)),  # -> conv3
                    nn.Sequential(*_conv(48, 64, 3, stride=2)),  # -> conv4
                    nn.Sequential(
                        nn.Flatten(), nn.Linear(64 * (h // m) * (w // m), 256), nn.ReLU()
                    ),  # -> fc
                    _PoseOut(256, anchors, spacing),  # -> vehicle (the pose)
                ]
            )
        assert len(self.stages) == len(SPLITS) - 1

    def _check_input(self, x: torch.Tensor) -> None:
        if x.dtype != torch.uint8 or x.ndim != 4 or tuple(x.shape[1:]) != self.image_shape:
            raise ValueError(
                f"LocNet takes uint8 images (N, {', '.join(map(str, self.image_shape))}), "
                f"got {x.dtype} {tuple(x.shape)}"
            )

    def head(self, split: int | str, x: torch.Tensor) -> torch.Tensor:
        """Vehicle side: stages [0:k] on a uint8 image batch; the activation at split `k`."""
        k = split_index(split)
        self._check_input(x)
        for stage in self.stages[:k]:
            x = stage(x)
        return x

    def tail(self, split: int | str, a: torch.Tensor) -> torch.Tensor:
        """Edge side: stages [k:] on the activation at split `k`; the (N, 4) pose output."""
        k = split_index(split)
        if k == 0:
            self._check_input(a)
        for stage in self.stages[k:]:
            a = stage(a)
        return a

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.tail(0, x)

    def tail_with_entropy(
        self, split: int | str, a: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """`tail(split, a)` and, per row, the entropy (nats) of the place classifier's softmax
        over all anchors: the DNN's own doubt about where it is. Not for the `vehicle` split,
        whose activation is the output itself: there the vehicle takes it from `fc`."""
        k = split_index(split)
        if k == len(self.stages):
            raise ValueError("the vehicle split's activation is the pose: no logits left to read")
        if k == 0:
            self._check_input(a)
        for stage in self.stages[k:-1]:
            a = stage(a)
        logits, xy, cs = self.pose_layer.parts(a)
        return torch.cat([xy, cs], dim=1), place_entropy(logits)

    def vehicle_side(
        self, split: int | str, x: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """What the vehicle computes for a request at `split`: `head(split, x)` and, for the
        `vehicle` split, whose activation is the pose itself, the place entropy that only the
        vehicle can read (None at every other split: the edge reads it, `edge_side`). One pass
        either way; the activation is the same as `head`'s."""
        if split_index(split) < len(self.stages):
            return self.head(split, x), None
        fc = SPLITS[-2]
        return self.tail_with_entropy(fc, self.head(fc, x))

    def edge_side(
        self, split: int | str, a: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """What the edge computes for an activation at `split`: `tail(split, a)` and the place
        entropy per row (None for the `vehicle` split: `vehicle_side` has it)."""
        if split_index(split) < len(self.stages):
            return self.tail_with_entropy(split, a)
        return self.tail(split, a), None

    @property
    def pose_layer(self) -> _PoseOut:
        return self.stages[-1]

    def activation_shape(self, split: int | str) -> tuple[int, ...]:
        """Shape of one frame's activation at `split` (no batch dimension)."""
        with torch.no_grad():
            was = self.training
            self.eval()
            a = self.head(split, torch.zeros((1, *self.image_shape), dtype=torch.uint8))
            self.train(was)
        return tuple(a.shape[1:])


def to_pose(out: torch.Tensor) -> torch.Tensor:
    """(N, 4) network output -> (N, 3) [x, y, yaw] poses."""
    return torch.stack([out[:, 0], out[:, 1], torch.atan2(out[:, 3], out[:, 2])], dim=1)


def place_entropy(logits: torch.Tensor) -> torch.Tensor:
    """(N, A) anchor logits -> (N,) entropy of their softmax in nats (0: one place, certain)."""
    logp = torch.log_softmax(logits, dim=1)
    return -(logp.exp() * logp).sum(dim=1)
