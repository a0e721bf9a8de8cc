"""The split-able DNN, its codecs, and the committed trained weights."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.stats
import torch

from nodes.edgeloc import codec
from nodes.edgeloc.dataset import SyntheticDataset
from nodes.edgeloc.fusion import ConfidenceMissing, ConfidenceWeight
from nodes.edgeloc.model import IMAGE_SHAPE, INPUT_POOL, SPLITS, LocNet, split_index, to_pose
from nodes.edgeloc.settings import confidence_file
from nodes.edgeloc.train import (
    HELD_OUT_SEEDS,
    METRICS_FILE,
    WEIGHTS_DIR,
    WEIGHTS_FILE,
    TrainConfig,
    WeightsMissing,
    entropy_calibration,
    evaluate,
    held_out_frames,
    load_model,
    write_confidence,
)


@pytest.fixture(scope="module")
def frames() -> np.ndarray:
    ds = SyntheticDataset(seed=9, duration_s=2.0)
    return np.stack([ds.image(i) for i in range(0, len(ds), 10)])


@pytest.fixture(scope="module")
def net() -> LocNet:
    return LocNet(seed=1).eval()


def test_split_points_are_named_and_sized(net: LocNet) -> None:
    assert len(SPLITS) >= 5 and SPLITS[0] == "image" and SPLITS[-1] == "vehicle"
    sizes = [int(np.prod(net.activation_shape(s))) for s in SPLITS]
    image = int(np.prod(IMAGE_SHAPE))
    net_input = image // INPUT_POOL**2  # the first stage averages INPUT_POOL² pixel blocks
    assert sizes[0] == image and sizes[-1] == 4
    assert any(s > net_input for s in sizes[1:-1])  # an early conv bigger than its input
    assert all(s < image for s in sizes[1:-1])  # but every activation smaller than the frame
    assert any(s < image / 16 for s in sizes[1:-1])  # later ones much smaller
    assert split_index("conv2") == 2 and split_index(3) == 3
    with pytest.raises(ValueError, match="unknown split point 'conv9'"):
        split_index("conv9")


@pytest.mark.parametrize("split", SPLITS)
def test_head_then_tail_equals_forward(net: LocNet, frames: np.ndarray, split: str) -> None:
    x = torch.from_numpy(frames)
    with torch.no_grad():
        full = net(x)
        parts = net.tail(split, net.head(split, x))
    assert torch.equal(full, parts)
    assert full.shape == (len(frames), 4)
    assert torch.allclose(full[:, 2:].norm(dim=1), torch.ones(len(frames)), atol=1e-5)


def test_init_is_deterministic(frames: np.ndarray) -> None:
    a, b, c = LocNet(seed=1).eval(), LocNet(seed=1).eval(), LocNet(seed=2).eval()
    x = torch.from_numpy(frames)
    with torch.no_grad():
        assert torch.equal(a(x), b(x)) and not torch.equal(a(x), c(x))


def test_bad_input_is_refused(net: LocNet) -> None:
    with pytest.raises(ValueError, match="uint8 images"):
        net(torch.zeros((1, 3, 48, 64)))


@pytest.mark.parametrize("name", codec.CODECS)
@pytest.mark.parametrize("split", SPLITS)
def test_codec_round_trip_within_bound(
    net: LocNet, frames: np.ndarray, name: str, split: str
) -> None:
    with torch.no_grad():
        a = net.head(split, torch.from_numpy(frames[:2]))
    blob = codec.encode(a, name)
    b = codec.decode(blob)
    assert b.shape == a.shape
    if a.dtype == torch.uint8 or a.numel() <= codec.SMALL:
        assert torch.equal(b.to(a.dtype), a)  # images and poses travel exactly
    else:
        err = (b - a).abs().max().item()
        assert err <= codec.error_bound(a, name)
        assert err > 0 or name == "fp16-zlib"  # int8 really quantises
    # smaller on the wire than raw float32 for every float activation
    if a.dtype != torch.uint8 and a.numel() > codec.SMALL:
        assert len(blob) < a.numel() * 4


def test_int8_is_smaller_than_fp16(net: LocNet, frames: np.ndarray) -> None:
    with torch.no_grad():
        a = net.head("conv2", torch.from_numpy(frames[:1]))
    assert len(codec.encode(a, "int8-zlib")) < len(codec.encode(a, "fp16-zlib"))


def test_codec_errors_are_clear() -> None:
    with pytest.raises(codec.CodecError, match="unknown codec 'gzip'"):
        codec.encode(torch.zeros(3), "gzip")
    with pytest.raises(codec.CodecError, match="not an activation blob"):
        codec.decode(b"hello world!")
    blob = codec.encode(torch.rand(100), "fp16-zlib")
    with pytest.raises(codec.CodecError, match="corrupt"):
        codec.decode(blob[:-5])


def test_split_table_measures_every_split(net: LocNet, frames: np.ndarray) -> None:
    table = codec.split_table(net, frames[:3])
    assert list(table) == list(SPLITS)
    for name in SPLITS:
        for c in codec.CODECS:
            assert 0 < table[name][c] <= table[name]["raw"] + 64


# ---- the committed, trained weights ----------------------------------------------------------


def test_committed_weights_exist_and_are_small() -> None:
    path = WEIGHTS_DIR / WEIGHTS_FILE
    assert path.is_file(), "run `make model` to train the DNN"
    assert path.stat().st_size < 2_000_000


def test_committed_metrics_record_quality() -> None:
    metrics = json.loads((WEIGHTS_DIR / METRICS_FILE).read_text())
    held = metrics["held_out"]
    assert held["median_translation_m"] < 5.0 and held["median_rotation_deg"] < 5.0
    assert list(metrics["split_bytes"]) == list(SPLITS)
    for name in SPLITS:
        for c in codec.CODECS:
            assert codec.encoded_size(name, c) == metrics["split_bytes"][name][c]


def test_committed_weights_localize_a_held_out_drive() -> None:
    model = load_model()
    ds = SyntheticDataset(seed=HELD_OUT_SEEDS[0], duration_s=30.0)
    idx = list(range(0, len(ds), 4))
    images = np.stack([ds.image(i) for i in idx])
    errors = evaluate(model, images, ds.gt_poses[idx])
    extent = np.ptp(ds.town.boxes[:, [0, 2]])
    median = float(np.median(errors.translation_m))
    outliers = float(np.mean(errors.translation_m > 10))
    print(f"held-out drive: median {median:.2f} m, outliers {outliers:.1%}")
    assert median < extent / 40  # ~10 m in a 400 m town: it knows where it is
    assert np.median(errors.rotation_deg) < 10.0
    # far better than guessing the town centre
    guess = np.median(np.hypot(ds.gt_poses[idx, 0], ds.gt_poses[idx, 1]))
    assert median < guess / 5


def test_missing_weights_say_how_to_make_them(tmp_path: Path) -> None:
    with pytest.raises(WeightsMissing, match="make model"):
        load_model(tmp_path / "none.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a model")
    with pytest.raises(WeightsMissing, match="make model"):
        load_model(bad)


def test_to_pose_gives_yaw() -> None:
    out = torch.tensor([[1.0, 2.0, 0.0, 1.0]])
    assert torch.allclose(to_pose(out), torch.tensor([[1.0, 2.0, np.pi / 2]]))


def test_first_stage_averages_the_camera_down_to_the_network_input() -> None:
    net = LocNet(seed=1).eval()
    assert net.pool == INPUT_POOL and IMAGE_SHAPE[0] % (16 * INPUT_POOL) == 0
    x = torch.randint(0, 256, (2, *IMAGE_SHAPE), dtype=torch.uint8)
    with torch.no_grad():
        pooled = net.stages[0][0](x)
        full = net.stages[0][0].__class__(1)(x)
    h, w = IMAGE_SHAPE[0] // INPUT_POOL, IMAGE_SHAPE[1] // INPUT_POOL
    assert pooled.shape == (2, 3, h, w)
    assert torch.allclose(pooled, torch.nn.functional.avg_pool2d(full, INPUT_POOL))
    with pytest.raises(ValueError, match="multiples of 32"):
        LocNet((48, 64, 3), pool=2)  # 24x32 after pooling cannot take four stride-2 convs
    LocNet((48, 64, 3), pool=1)  # the same network on a camera of its input size


def test_camera_frame_travels_stored_activations_compressed(frames: np.ndarray) -> None:
    """The raw frame is sent without compression (zlib saves little on a noisy frame and the
    vehicle's slow CPU would pay for it); activations are compressed as before."""
    blob = codec.encode(torch.from_numpy(frames[:1]), "fp16-zlib")
    assert frames[:1].nbytes < len(blob) <= frames[:1].nbytes + 64
    assert torch.equal(codec.decode(blob), torch.from_numpy(frames[:1]))
    a = torch.zeros((1, 48, 6, 8))
    assert len(codec.encode(a, "fp16-zlib")) < a.numel() * 2 / 10


@pytest.mark.parametrize("split", SPLITS[:-1])
def test_the_tail_reads_the_place_classifiers_entropy_beside_the_pose(
    net: LocNet, frames: np.ndarray, split: str
) -> None:
    """The same output as `tail`, and the entropy torch's own Categorical gives the logits."""
    x = torch.from_numpy(frames)
    with torch.no_grad():
        a = net.head(split, x)
        out, entropy = net.tail_with_entropy(split, a)
        feats = net.head(SPLITS[-2], x)
        logits = net.pose_layer.parts(feats)[0]
    assert torch.equal(out, net.tail(split, a))
    oracle = torch.distributions.Categorical(logits=logits).entropy()
    torch.testing.assert_close(entropy, oracle, rtol=1e-5, atol=1e-5)
    assert bool((entropy >= 0).all()) and bool((entropy <= np.log(logits.shape[1])).all())


def test_the_vehicle_split_has_no_logits_left_for_the_edge(net: LocNet, frames: np.ndarray) -> None:
    with torch.no_grad(), pytest.raises(ValueError, match="no logits"):
        net.tail_with_entropy("vehicle", net(torch.from_numpy(frames)))


def test_the_committed_dnns_entropy_tells_its_error_on_held_out_drives() -> None:
    """Calibrated on frames training never saw: the less sure the DNN is of the place, the
    larger its error, by band medians and in rank over every frame; the fitted weight says so."""
    model = load_model()
    images, gt = held_out_frames(TrainConfig(eval_stride=6))
    weight, bands = entropy_calibration(model, images, gt, bands=5)
    print(weight, [(round(b.hi_nats, 2), round(b.median_error_m, 2)) for b in bands])
    assert sum(b.frames for b in bands) == len(images)
    assert bands[-1].median_error_m > 2.5 * bands[0].median_error_m
    assert bands[-1].outlier_share > max(b.outlier_share for b in bands[:-1])
    assert weight.per_nat > 0.5
    lo, hi = bands[0].lo_nats, bands[-1].hi_nats
    assert lo < weight.reference_nats < hi
    with torch.no_grad():  # one pass gives the pose and the entropy
        fc = SPLITS[-2]
        out, entropy = model.tail_with_entropy(fc, model.head(fc, torch.from_numpy(images)))
    err = np.hypot(*(out[:, :2].numpy() - gt[:, :2]).T)
    assert scipy.stats.spearmanr(entropy.numpy(), err).statistic > 0.25


def test_the_committed_confidence_calibration_is_the_fit_of_the_committed_weights(
    tmp_path: Path,
) -> None:
    """weights/confidence.json (what a scenario's `fusion.confidence` reads) is what fitting
    the committed weights on every held-out frame gives now; `--calibrate` writes one that reads
    back the same, and a missing or foreign file is refused with the command that makes it."""
    committed = ConfidenceWeight.read(confidence_file(None))
    model = load_model()
    images, gt = held_out_frames(TrainConfig())
    path, fitted = write_confidence(model, images, gt, tmp_path)
    assert path == confidence_file(tmp_path / WEIGHTS_FILE)
    assert ConfidenceWeight.read(path) == fitted
    assert fitted.per_nat == pytest.approx(committed.per_nat, rel=1e-3)
    assert fitted.reference_nats == pytest.approx(committed.reference_nats, rel=1e-3)
    bands = json.loads(path.read_text())["bands"]
    assert sum(b["frames"] for b in bands) == len(images) and len(bands) == 10
    with pytest.raises(ConfidenceMissing, match="--calibrate --out"):
        ConfidenceWeight.read(tmp_path / "nothing" / "confidence.json")
    path.write_text('{"per_nat": -1, "reference_nats": 1}')
    with pytest.raises(ConfidenceMissing, match="not a confidence calibration"):
        ConfidenceWeight.read(path)


@pytest.mark.parametrize("split", SPLITS)
def test_exactly_one_side_reads_the_doubt_and_the_vehicle_sends_what_head_gives(
    net: LocNet, frames: np.ndarray, split: str
) -> None:
    """`vehicle_side` sends `head`'s activation bit for bit; the entropy comes from the edge,
    or from the vehicle at the vehicle split, and equals torch's own of the place logits."""
    x = torch.from_numpy(frames)
    with torch.no_grad():
        act, mine = net.vehicle_side(split, x)
        out, theirs = net.edge_side(split, act)
        logits = net.pose_layer.parts(net.head(SPLITS[-2], x))[0]
        assert torch.equal(act, net.head(split, x))
        assert torch.equal(out, net(x))
    assert (mine is None) != (theirs is None) and (mine is None) == (split != "vehicle")
    entropy = mine if mine is not None else theirs
    oracle = torch.distributions.Categorical(logits=logits).entropy()
    torch.testing.assert_close(entropy, oracle, rtol=1e-5, atol=1e-5)
