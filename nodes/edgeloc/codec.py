"""Wire format of a split activation: what the vehicle sends to the edge at split point `k`.

A codec turns one activation tensor into bytes and back. Two lossy codecs for float
activations, named as in the scenario's `workload.codec`:

- `fp16-zlib`: cast to float16 (values clamped to ±65504), then zlib. Error per value
  <= |x| * 2**-11 + 2**-24.
- `int8-zlib`: per-tensor affine quantisation to 256 levels, `q = round((x - zero_point) /
  scale)` with `zero_point = min(x)`, `scale = (max(x) - min(x)) / 255`, then zlib. Error per
  value <= scale / 2 (plus float32 rounding). ReLU zeros stay exactly zero (zero_point = 0).

Two tensors are sent exactly whatever the codec: uint8 tensors (the `image` split: the camera
frame as captured, stored in a zlib frame without compression, see `IMAGE_ZLIB_LEVEL`) and tiny
float tensors of <= 16 values (the `vehicle` split: the pose itself, float32: quantising 4
numbers would add error and save nothing).

Each blob is self-describing: `b"EA"`, version, kind, ndim, shape (uint32 each), for int8 the
scale and zero point (float32), then the zlib payload. `decode(encode(a))` needs no side
information. `split_table()` measures bytes per split on real activations and
`encoded_size()` reads the table measured when the committed weights were trained.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Sequence
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from nodes.edgeloc.errors import EdgeLocError

if TYPE_CHECKING:
    from nodes.edgeloc.model import LocNet

CODECS: tuple[str, ...] = ("fp16-zlib", "int8-zlib")
SMALL = 16  # float tensors up to this many values are sent as float32
ZLIB_LEVEL = 1  # fast: compression time adds to the latency the learner minimises
# Camera frames (uint8) go stored (zlib level 0: framing and checksum, no compression). With
# sensor noise zlib level 1 saves only ~26% of a 128x96 frame (27.4 of 36.9 kB on the synthetic
# drive) and takes ~1.5 ms of one full core here; on the vehicle's budget (0.025 cores in the
# default scenario stretches that 40x) the compression costs far more time (60 ms) than the
# 9.5 kB it saves on even a 2 Mbit/s uplink (38 ms). Activations compress well (ReLU zeros) and stay
# at ZLIB_LEVEL.
IMAGE_ZLIB_LEVEL = 0
_MAGIC, _VERSION = b"EA", 1
_RAW_U8, _FP16, _INT8, _FP32 = 0, 1, 2, 3
_HEAD = struct.Struct("<2sBBB")
_METRICS = Path(__file__).resolve().parent / "weights" / "metrics.json"


class CodecError(EdgeLocError, ValueError):
    """A codec name or a blob that cannot be used."""


def _check_codec(codec: str) -> None:
    if codec not in CODECS:
        raise CodecError(f"unknown codec {codec!r}; known: {', '.join(CODECS)}")


def encode(a: torch.Tensor | np.ndarray, codec: str, level: int = ZLIB_LEVEL) -> bytes:
    """The bytes that carry activation `a` (any shape) under `codec`."""
    _check_codec(codec)
    x = a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)
    if x.ndim > 8 or any(d >= 2**32 for d in x.shape):
        raise CodecError(f"cannot encode a tensor of shape {x.shape}")
    extra = b""
    if x.dtype == np.uint8:
        kind, body = _RAW_U8, x
    elif not np.issubdtype(x.dtype, np.floating):
        raise CodecError(f"activations are uint8 images or floats, got {x.dtype}")
    elif x.size <= SMALL:
        kind, body = _FP32, x.astype("<f4")
    elif codec == "fp16-zlib":
        kind, body = _FP16, np.clip(x, -65504.0, 65504.0).astype("<f2")
    else:
        kind = _INT8
        x = x.astype(np.float32)
        lo, hi = (float(x.min()), float(x.max())) if x.size else (0.0, 0.0)
        scale = (hi - lo) / 255.0 if hi > lo else 1.0
        body = np.clip(np.rint((x - lo) / scale), 0, 255).astype(np.uint8)
        extra = struct.pack("<ff", scale, lo)
    shape = struct.pack(f"<{x.ndim}I", *x.shape)
    if kind == _RAW_U8:
        level = IMAGE_ZLIB_LEVEL
    payload = zlib.compress(np.ascontiguousarray(body).tobytes(), level)
    return _HEAD.pack(_MAGIC, _VERSION, kind, x.ndim) + shape + extra + payload


def decode(blob: bytes) -> torch.Tensor:
    """The activation carried by `blob` (float32, or uint8 for an image)."""
    if len(blob) < _HEAD.size:
        raise CodecError(f"blob of {len(blob)} bytes is too short to be an activation")
    magic, version, kind, ndim = _HEAD.unpack_from(blob)
    if magic != _MAGIC or version != _VERSION or kind > _FP32:
        raise CodecError("not an activation blob (bad magic, version or kind)")
    off = _HEAD.size
    shape = struct.unpack_from(f"<{ndim}I", blob, off)
    off += 4 * ndim
    scale = lo = 0.0
    if kind == _INT8:
        scale, lo = struct.unpack_from("<ff", blob, off)
        off += 8
    try:
        raw = zlib.decompress(blob[off:])
    except zlib.error as e:
        raise CodecError(f"corrupt activation payload ({e})") from None
    dtype = {_RAW_U8: np.uint8, _FP16: "<f2", _INT8: np.uint8, _FP32: "<f4"}[kind]
    x = np.frombuffer(raw, dtype=dtype)
    if x.size != int(np.prod(shape)):
        raise CodecError(f"payload has {x.size} values for shape {shape}")
    x = x.reshape(shape)
    if kind == _RAW_U8:
        return torch.from_numpy(x.copy())
    if kind == _INT8:
        return torch.from_numpy(x.astype(np.float32) * np.float32(scale) + np.float32(lo))
    return torch.from_numpy(x.astype(np.float32))


def error_bound(a: torch.Tensor | np.ndarray, codec: str) -> float:
    """The largest |decode(encode(a)) - a| the codec allows for this tensor."""
    _check_codec(codec)
    x = a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)
    if x.dtype == np.uint8 or x.size == 0:
        return 0.0
    x = x.astype(np.float32)
    big = float(np.abs(x).max())
    if x.size <= SMALL:
        return 0.0
    if codec == "fp16-zlib":
        return big * 2.0**-11 + 2.0**-24
    span = float(x.max() - x.min())
    return span / 255.0 / 2.0 + 4 * big * 2.0**-23  # half a step, plus float32 rounding


@torch.no_grad()
def split_table(
    model: LocNet, images: np.ndarray, codecs: Sequence[str] = CODECS
) -> dict[str, dict[str, object]]:
    """Bytes per frame at every split under each codec, measured on `images` (N, H, W, 3).

    Per split: the activation shape, its raw size (uint8 image or float32) and the median
    encoded size under each codec."""
    from nodes.edgeloc.model import SPLITS

    model.eval()
    table: dict[str, dict[str, object]] = {}
    frames = [torch.from_numpy(np.ascontiguousarray(im[None])) for im in images]
    for k, name in enumerate(SPLITS):
        acts = [model.head(k, f) for f in frames]
        a0 = acts[0]
        row: dict[str, object] = {
            "shape": list(a0.shape[1:]),
            "raw": int(a0.numel() * a0.element_size()),
        }
        for c in codecs:
            row[c] = int(np.median([len(encode(a, c)) for a in acts]))
        table[name] = row
    return table


@cache
def _committed_table() -> dict[str, dict[str, object]]:
    if not _METRICS.is_file():
        raise FileNotFoundError(f"{_METRICS} is missing: run `make model` to train the DNN")
    return json.loads(_METRICS.read_text())["split_bytes"]


def encoded_size(split: str, codec: str = "fp16-zlib") -> int:
    """Median bytes per frame at `split` under `codec`, as measured for the committed model."""
    _check_codec(codec)
    table = _committed_table()
    if split not in table:
        raise CodecError(f"unknown split point {split!r}; known: {', '.join(table)}")
    return int(table[split][codec])
