"""Train the localization DNN on the synthetic town, reproducibly, and write its weights.

    python -m nodes.edgeloc.train [--seed S] [--out DIR] [--samples N] [--epochs E]

Training frames are camera poses sampled all over the town's streets (both directions, both
lanes, turning at intersections) under random time of day, weather and trucks: many drives'
worth of views, like PoseNet's training traversals. The held-out frames are whole drives
(`SyntheticDataset` with seeds the sampler never uses), so the reported errors are those the
workload will see: they come from the model on images (look-alike streets, dusk, trucks in
front), not from injected noise.

Writes `<out>/locnet.pt` (a state_dict) and `<out>/metrics.json` (held-out median translation
and rotation error, outlier rate, training time and bytes per split under each codec).
`load_model()` loads the committed weights from this package's `weights/` folder.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from numpy.typing import NDArray

from nodes.edgeloc import geometry as se2
from nodes.edgeloc.codec import CODECS, split_table
from nodes.edgeloc.dataset import SyntheticDataset
from nodes.edgeloc.errors import EdgeLocError
from nodes.edgeloc.fusion import ConfidenceWeight
from nodes.edgeloc.latency import ComputeProfile
from nodes.edgeloc.model import IMAGE_SHAPE, SPLITS, LocNet, street_anchors, to_pose
from nodes.edgeloc.settings import CONFIDENCE_FILE, WEIGHTS_DIR
from nodes.edgeloc.world import DEFAULT_TOWN_SEED, Camera, Lighting, Obstacle, Town

WEIGHTS_FILE = "locnet.pt"
METRICS_FILE = "metrics.json"
COMPUTE_FILE = "compute.json"  # the reference compute profile (see latency.ComputeProfile)
HELD_OUT_SEEDS = (101, 102, 103)  # drives never used for training
OUTLIER_M = 10.0  # a DNN pose this far off counts as an outlier


class WeightsMissing(EdgeLocError, FileNotFoundError):
    """The trained weights are not where they should be."""


@dataclass(frozen=True)
class TrainConfig:
    """What one training run does; every field is recorded in metrics.json."""

    seed: int = 0
    town_seed: int = DEFAULT_TOWN_SEED
    samples: int = 48000  # rendered training frames
    epochs: int = 20
    batch: int = 64
    lr: float = 2e-3
    spacing: float = 15.0  # metres between street anchors of the place classifier
    threads: int = 2
    eval_stride: int = 2  # evaluate every n-th frame of the held-out drives
    eval_duration_s: float = 90.0


# ---- training frames -------------------------------------------------------------------------


def sample_poses(town: Town, rng: np.random.Generator, n: int) -> NDArray[np.float64]:
    """`n` camera poses on the streets: any lane, both directions, turning at crossings."""
    roads = town.road_coords()
    lo, hi = roads[0] - 10.0, roads[-1] + 10.0
    along_x = rng.random(n) < 0.5  # a street running along x (at y = road) or along y
    road = roads[rng.integers(0, len(roads), n)]
    u = rng.uniform(lo, hi, n)
    lateral = rng.uniform(-5.5, 5.5, n)
    forward = rng.random(n) < 0.5
    heading = np.where(along_x, np.where(forward, 0.0, np.pi), np.where(forward, 0.5, -0.5) * np.pi)
    heading = heading + rng.normal(0.0, 0.06, n)
    near = np.min(np.abs(u[:, None] - roads[None]), axis=1) < 12.0
    turning = near & (rng.random(n) < 0.5)
    heading = np.where(turning, rng.uniform(-np.pi, np.pi, n), heading)
    x = np.where(along_x, u, road + lateral)
    y = np.where(along_x, road + lateral, u)
    return np.stack([x, y, np.asarray(se2.wrap(heading))], axis=1)


def _render_chunk(args: tuple[int, int, NDArray[np.float64], int]) -> NDArray[np.uint8]:
    """Render training frames [start, start+len(poses)) (in a worker process)."""
    town_seed, seed, poses, start = args
    torch.set_num_threads(1)
    town = Town.generate(town_seed)
    cam = Camera(town, width=IMAGE_SHAPE[1], height=IMAGE_SHAPE[0])
    out = np.empty((len(poses), *IMAGE_SHAPE), dtype=np.uint8)
    for j, p in enumerate(poses):
        rng = np.random.default_rng([seed, 7, start + j])  # per frame, order-independent
        light = Lighting.at(rng.uniform(0.0, 1.0), rng.uniform(0.0, 1.0))
        obstacles = []
        if rng.random() < 0.25:  # a truck ahead in our lane
            off = np.array([rng.uniform(11.0, 22.0), rng.uniform(-0.6, 0.6), rng.normal(0, 0.05)])
            obstacles.append(Obstacle(se2.compose(p, off), colour=_truck_colour(rng)))
        if rng.random() < 0.1:  # one coming the other way
            off = np.array([rng.uniform(4.0, 30.0), rng.uniform(5.5, 8.0), np.pi])
            obstacles.append(Obstacle(se2.compose(p, off), colour=_truck_colour(rng)))
        out[j] = cam.render(p, light, obstacles, noise_rng=rng)
    return out


def _truck_colour(rng: np.random.Generator) -> tuple[float, float, float]:
    c = rng.uniform(0.1, 0.9, 3)
    return (float(c[0]), float(c[1]), float(c[2]))


def render_frames(
    town_seed: int, seed: int, poses: NDArray[np.float64], workers: int
) -> NDArray[np.uint8]:
    """Training images for `poses`; identical whatever the number of worker processes."""
    chunks = np.array_split(np.arange(len(poses)), max(workers, 1) * 4)
    jobs = [(town_seed, seed, poses[c], int(c[0])) for c in chunks if len(c)]
    if workers <= 1:
        return np.concatenate([_render_chunk(j) for j in jobs])
    with ProcessPoolExecutor(workers) as pool:
        return np.concatenate(list(pool.map(_render_chunk, jobs)))


# ---- evaluation ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Errors:
    """Per-frame DNN errors on held-out drives."""

    translation_m: NDArray[np.float64]
    rotation_deg: NDArray[np.float64]

    def summary(self) -> dict[str, float]:
        t, r = self.translation_m, self.rotation_deg
        return {
            "frames": len(t),
            "median_translation_m": float(np.median(t)),
            "mean_translation_m": float(np.mean(t)),
            "p90_translation_m": float(np.percentile(t, 90)),
            "median_rotation_deg": float(np.median(r)),
            "outlier_rate": float(np.mean(t > OUTLIER_M)),
            "outlier_threshold_m": OUTLIER_M,
        }


@torch.no_grad()
def predict(model: LocNet, images: NDArray[np.uint8], batch: int = 256) -> NDArray[np.float64]:
    """(N, 3) poses for a stack of uint8 images."""
    model.eval()
    out = [
        to_pose(model(torch.from_numpy(np.ascontiguousarray(images[i : i + batch])))).numpy()
        for i in range(0, len(images), batch)
    ]
    return np.concatenate(out).astype(np.float64)


def held_out_frames(cfg: TrainConfig) -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
    images, poses = [], []
    for s in HELD_OUT_SEEDS:
        ds = SyntheticDataset(s, 20.0, cfg.eval_duration_s, town_seed=cfg.town_seed)
        idx = range(0, len(ds), cfg.eval_stride)
        images += [ds.image(i) for i in idx]
        poses.append(ds.gt_poses[:: cfg.eval_stride])
    return np.stack(images), np.concatenate(poses)


def evaluate(model: LocNet, images: NDArray[np.uint8], gt: NDArray[np.float64]) -> Errors:
    est = predict(model, images)
    t = np.hypot(est[:, 0] - gt[:, 0], est[:, 1] - gt[:, 1])
    r = np.degrees(np.abs(np.asarray(se2.wrap(est[:, 2] - gt[:, 2]))))
    return Errors(t, r)


@dataclass(frozen=True)
class EntropyBand:
    """Held-out frames whose place entropy lies in [lo_nats, hi_nats], and the DNN's error there."""

    lo_nats: float
    hi_nats: float
    frames: int
    median_error_m: float
    outlier_share: float  # answers more than OUTLIER_M off


def entropy_calibration(
    model: LocNet, images: NDArray[np.uint8], gt: NDArray[np.float64], bands: int = 10
) -> tuple[ConfidenceWeight, tuple[EntropyBand, ...]]:
    """How well the DNN's place entropy tells its error, on held-out frames: the median error
    and the outlier share per entropy band (equal counts), and the fusion's confidence weight.

    The weight scales an answer by its error variance against the median answer's:
    log(median error) ≈ a + b·H over the bands' medians (medians, so the outliers that the
    robust term handles do not set it), per_nat = 2b, reference = the median entropy.
    """
    model.eval()
    pos, ent = [], []
    with torch.no_grad():
        for i in range(0, len(images), 256):
            x = torch.from_numpy(np.ascontiguousarray(images[i : i + 256]))
            out, h = model.vehicle_side(SPLITS[-1], x)  # the whole net, logits read on the way
            assert h is not None
            pos.append(out[:, :2].numpy())
            ent.append(h.numpy())
    h = np.concatenate(ent).astype(np.float64)
    err = np.hypot(*(np.concatenate(pos) - gt[:, :2]).T)
    edges = np.quantile(h, np.linspace(0.0, 1.0, bands + 1))
    which = np.clip(np.searchsorted(edges, h, side="right") - 1, 0, bands - 1)
    table, mids = [], []
    for j in range(bands):
        e = err[which == j]
        if not len(e):
            continue
        mids.append(float(np.median(h[which == j])))
        table.append(
            EntropyBand(
                float(edges[j]), float(edges[j + 1]), len(e), float(np.median(e)),
                float(np.mean(e > OUTLIER_M)),
            )
        )  # fmt: skip
    slope, _ = np.polyfit(mids, np.log([b.median_error_m for b in table]), 1)
    weight = ConfidenceWeight(max(2.0 * float(slope), 0.0), float(np.median(h)))
    return weight, tuple(table)


def write_confidence(
    model: LocNet, images: NDArray[np.uint8], gt: NDArray[np.float64], weights_dir: Path
) -> tuple[Path, ConfidenceWeight]:
    """Fit the confidence weight of `model` on held-out frames (`entropy_calibration`) and
    write it beside its weights (`CONFIDENCE_FILE`, read by `ConfidenceWeight.read`), with the
    entropy bands it was fitted on."""
    weight, bands = entropy_calibration(model, images, gt)
    path = weights_dir / CONFIDENCE_FILE
    record = {
        "per_nat": weight.per_nat,
        "reference_nats": weight.reference_nats,
        "fitted": (
            "train.entropy_calibration: log(median error) ~ a + b*H over ten equal-count "
            "entropy bands of the held-out drives; per_nat = 2b, reference = the median H"
        ),
        "held_out_seeds": list(HELD_OUT_SEEDS),
        "bands": [b.__dict__ for b in bands],
        "torch": torch.__version__,
    }
    path.write_text(json.dumps(record, indent=2) + "\n")
    return path, weight


# ---- training --------------------------------------------------------------------------------


def _loss(
    model: LocNet, features: torch.Tensor, target: torch.Tensor, soft: torch.Tensor
) -> torch.Tensor:
    """Place classification (soft labels over nearby anchors), the position the layer outputs
    (robust, in units of 5 m) and heading error on the unit circle."""
    logits, xy, cs = model.pose_layer.parts(features)
    place = -(soft * torch.log_softmax(logits, dim=1)).sum(dim=1).mean()
    pos = torch.nn.functional.smooth_l1_loss(xy / 5.0, target[:, :2] / 5.0)
    yaw = ((cs - target[:, 2:]) ** 2).sum(dim=1).mean()
    return place + pos + 4.0 * yaw


def soft_labels(anchors: torch.Tensor, xy: torch.Tensor, spacing: float) -> torch.Tensor:
    """Target distribution over anchors: a Gaussian of the distance, sigma = spacing / 2."""
    d2 = torch.cdist(xy, anchors) ** 2
    p = torch.softmax(-d2 / (2 * (spacing / 2) ** 2), dim=1)
    return p


def train(cfg: TrainConfig, log=print) -> tuple[LocNet, dict]:
    """Render, fit and evaluate; returns the model (eval mode) and its metrics."""
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    torch.use_deterministic_algorithms(True)
    t_start = time.perf_counter()
    town = Town.generate(cfg.town_seed)
    rng = np.random.default_rng([cfg.seed, 3])
    poses = sample_poses(town, rng, cfg.samples)
    images = render_frames(cfg.town_seed, cfg.seed, poses, workers=cfg.threads)
    t_render = time.perf_counter() - t_start
    log(f"rendered {len(images)} training frames in {t_render:.1f} s")

    anchors = street_anchors(town.road_coords(), cfg.spacing, margin=cfg.spacing)
    model = LocNet(IMAGE_SHAPE, anchors=anchors, spacing=cfg.spacing, seed=cfg.seed)
    target = np.concatenate([poses[:, :2], np.cos(poses[:, 2:]), np.sin(poses[:, 2:])], axis=1)
    x_all = torch.from_numpy(images)
    y_all = torch.from_numpy(target.astype(np.float32))
    soft_all = soft_labels(model.pose_layer.anchors, y_all[:, :2], cfg.spacing)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=1e-4)
    steps = cfg.epochs * (len(images) // cfg.batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, cfg.lr, total_steps=steps, pct_start=0.15)
    gen = torch.Generator().manual_seed(cfg.seed)
    eval_images, eval_gt = held_out_frames(cfg)
    t_fit = time.perf_counter()
    for epoch in range(cfg.epochs):
        model.train()
        order = torch.randperm(len(images), generator=gen)
        total, count = 0.0, 0
        for b in range(len(images) // cfg.batch):
            idx = order[b * cfg.batch : (b + 1) * cfg.batch]
            xb = x_all[idx]
            if torch.rand((), generator=gen) < 0.5:  # brightness jitter on top of the lighting
                gain = 0.75 + 0.5 * torch.rand((xb.shape[0], 1, 1, 1), generator=gen)
                xb = (xb.to(torch.float32) * gain).clamp(0, 255).to(torch.uint8)
            features = model.head(len(SPLITS) - 2, xb)  # up to the `fc` split
            loss = _loss(model, features, y_all[idx], soft_all[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total, count = total + loss.item(), count + 1
        quick = evaluate(model, eval_images[::8], eval_gt[::8]).summary()
        log(
            f"epoch {epoch + 1}/{cfg.epochs}: loss {total / max(count, 1):.4f}, held-out "
            f"median {quick['median_translation_m']:.1f} m, outliers {quick['outlier_rate']:.0%}"
            f" ({time.perf_counter() - t_fit:.0f} s)"
        )
    t_fit = time.perf_counter() - t_fit
    model.eval()
    errors = evaluate(model, eval_images, eval_gt)
    table = split_table(model, eval_images[:: max(len(eval_images) // 64, 1)])
    metrics = {
        "held_out": {"seeds": list(HELD_OUT_SEEDS), **errors.summary()},
        "train_time_s": round(time.perf_counter() - t_start, 1),
        "render_time_s": round(t_render, 1),
        "fit_time_s": round(t_fit, 1),
        "config": cfg.__dict__,
        "image_shape": list(IMAGE_SHAPE),
        "splits": list(SPLITS),
        "codecs": list(CODECS),
        "split_bytes": table,
        "parameters": sum(p.numel() for p in model.parameters()),
        "torch": torch.__version__,
        "python": platform.python_version(),
    }
    return model, metrics


def reevaluate(weights_dir: Path = WEIGHTS_DIR, log=print) -> dict:
    """Evaluate the weights in `weights_dir` again on the held-out drives with the current
    camera and codecs, and rewrite their metrics.json (held-out errors, bytes per split, image
    shape), keeping the training record (config, times). The reference compute profile beside
    them (`compute.json`) is measured again too.

    For a change of the camera or the codec that leaves the network's parameters as they are
    (the 128x96 camera feeds the same 64x48 network through its 2x2 mean), this reports what the
    committed weights do now without retraining them; `make model` retrains instead.
    """
    metrics_path = weights_dir / METRICS_FILE
    old = json.loads(metrics_path.read_text()) if metrics_path.is_file() else {}
    cfg = TrainConfig(**old.get("config", {}))
    torch.set_num_threads(cfg.threads)
    model = load_model(weights_dir / WEIGHTS_FILE)
    images, gt = held_out_frames(cfg)
    errors = evaluate(model, images, gt)
    table = split_table(model, images[:: max(len(images) // 64, 1)])
    metrics = {
        **old,
        "held_out": {"seeds": list(HELD_OUT_SEEDS), **errors.summary()},
        "evaluated": (
            f"held-out errors and split bytes re-measured for the {IMAGE_SHAPE[1]}x"
            f"{IMAGE_SHAPE[0]} camera without retraining; training record as it was"
        ),
        "image_shape": list(IMAGE_SHAPE),
        "splits": list(SPLITS),
        "codecs": list(CODECS),
        "split_bytes": table,
        "torch": torch.__version__,
        "python": platform.python_version(),
    }
    if "held_out" in old and "held_out_before" not in old:
        metrics["held_out_before"] = {"image_shape": old.get("image_shape"), **old["held_out"]}
    metrics_path.write_text(json.dumps(metrics, indent=2) + "\n")
    write_compute_profile(model, images[:30], weights_dir)
    write_confidence(model, images, gt, weights_dir)
    h = metrics["held_out"]
    log(
        f"held-out: median {h['median_translation_m']:.2f} m, outliers "
        f"{100 * h['outlier_rate']:.1f}%; wrote {metrics_path}, {COMPUTE_FILE} and "
        f"{CONFIDENCE_FILE}"
    )
    return metrics


def recorded_config(weights_dir: Path) -> TrainConfig:
    """The training settings recorded in the metrics.json of the weights in `weights_dir`."""
    return TrainConfig(**json.loads((weights_dir / METRICS_FILE).read_text()).get("config", {}))


def load_model(weights_path: str | os.PathLike | None = None) -> LocNet:
    """The trained LocNet in eval mode (default: the committed weights of this package)."""
    path = Path(weights_path) if weights_path is not None else WEIGHTS_DIR / WEIGHTS_FILE
    if not path.is_file():
        raise WeightsMissing(
            f"DNN weights not found at {path}: run `make model` "
            "(python -m nodes.edgeloc.train) to train them"
        )
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # a truncated or foreign file
        raise WeightsMissing(f"{path} is not a LocNet state_dict ({e}); run `make model`") from e
    anchors = state.get("stages.5.anchors") if isinstance(state, dict) else None
    if anchors is None:
        raise WeightsMissing(f"{path} is not a LocNet state_dict; run `make model`")
    model = LocNet(IMAGE_SHAPE, anchors=anchors, spacing=float(state["stages.5.spacing"]))
    try:
        model.load_state_dict(state)
    except RuntimeError as e:
        raise WeightsMissing(f"{path} does not fit this LocNet ({e}); run `make model`") from e
    return model.eval()


def drive_frames(town_seed: int, n: int = 30) -> NDArray[np.uint8]:
    """`n` consecutive camera frames of a drive (what a node's DNN head gets)."""
    ds = SyntheticDataset(0, duration_s=n / 20 + 0.5, town_seed=town_seed)
    return np.stack([ds.image(i) for i in range(n)])


def write_compute_profile(model: LocNet, frames: NDArray[np.uint8], weights_dir: Path) -> Path:
    """Measure the per-call compute profile the replay uses for these weights and write it
    beside them (see `latency.ComputeProfile.reference`)."""
    profile = ComputeProfile.measure_reference(model, frames, "fp16-zlib")
    path = weights_dir / COMPUTE_FILE
    path.write_text(json.dumps(profile.to_json(), indent=2) + "\n")
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m nodes.edgeloc.train", description=__doc__)
    p.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    p.add_argument("--out", type=Path, default=WEIGHTS_DIR, help="folder for weights + metrics")
    p.add_argument("--samples", type=int, default=TrainConfig.samples, help="training frames")
    p.add_argument("--epochs", type=int, default=TrainConfig.epochs)
    p.add_argument("--threads", type=int, default=TrainConfig.threads)
    p.add_argument(
        "--evaluate",
        action="store_true",
        help="do not train: evaluate the weights in --out again and rewrite their metrics",
    )
    p.add_argument(
        "--compute",
        action="store_true",
        help="do not train: measure the compute profile of the weights in --out again",
    )
    p.add_argument(
        "--calibrate",
        action="store_true",
        help="do not train: fit the confidence weight of the weights in --out on the held-out"
        f" drives again and write {CONFIDENCE_FILE}",
    )
    a = p.parse_args(argv)
    if a.calibrate:
        torch.set_num_threads(TrainConfig.threads)
        cfg = recorded_config(a.out)
        images, gt = held_out_frames(cfg)
        path, weight = write_confidence(load_model(a.out / WEIGHTS_FILE), images, gt, a.out)
        print(
            f"per_nat {weight.per_nat:.3f}/nat, reference {weight.reference_nats:.3f} nats; "
            f"wrote {path}"
        )
        return 0
    if a.compute:
        torch.set_num_threads(1)
        cfg = recorded_config(a.out)
        path = write_compute_profile(
            load_model(a.out / WEIGHTS_FILE), drive_frames(cfg.town_seed), a.out
        )
        print(f"wrote {path}")
        return 0
    if a.evaluate:
        reevaluate(a.out, log=lambda m: print(m, flush=True))
        return 0
    if a.samples < 256 or a.epochs < 1 or a.threads < 1:
        p.error("--samples must be >= 256, --epochs and --threads >= 1")
    cfg = TrainConfig(seed=a.seed, samples=a.samples, epochs=a.epochs, threads=a.threads)
    model, metrics = train(cfg, log=lambda m: print(m, flush=True))
    a.out.mkdir(parents=True, exist_ok=True)
    torch.save(model.state_dict(), a.out / WEIGHTS_FILE)
    (a.out / METRICS_FILE).write_text(json.dumps(metrics, indent=2) + "\n")
    write_compute_profile(model, drive_frames(cfg.town_seed), a.out)
    write_confidence(model, *held_out_frames(cfg), a.out)
    h = metrics["held_out"]
    print(
        f"held-out: median {h['median_translation_m']:.2f} m, {h['median_rotation_deg']:.2f} deg, "
        f"outliers {100 * h['outlier_rate']:.1f}% (> {OUTLIER_M:.0f} m); "
        f"{metrics['train_time_s']:.0f} s; wrote {a.out / WEIGHTS_FILE}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
