"""The DNN answers kept between reports (`nodes.edgeloc.answerstore`): what is read back is
what was stored, a change to what answers depend on is another key, and a comparison replayed
from stored answers is the one computed without them, without running the DNN."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from nodes.edgeloc.answerstore import AnswerStore, answers_key, cache_dir
from nodes.edgeloc.compare import answer_all, compare_splits
from nodes.edgeloc.model import LocNet
from nodes.edgeloc.replay import Answer, InferenceCache, config_dataset, drive_of
from nodes.edgeloc.train import load_model
from testbed.replay import latency_model, replay_config
from testbed.scenario import load

SMOKE = Path(__file__).resolve().parents[1] / "scenarios" / "smoke.yaml"


def test_stored_answers_read_back_as_they_were(tmp_path: Path) -> None:
    answers = {
        (0, "image"): Answer(np.array([1.5, -2.25, 0.125]), 1200, 0.5),
        (0, "conv3"): Answer(np.array([1.0, 2.0, 3.0]), 33, None),
        (7, "image"): Answer(np.array([np.pi, 1e-300, -0.0]), 9, 2.0),
    }
    store = AnswerStore("k", tmp_path)
    assert store.load() == {}
    store.save(answers)
    back = AnswerStore("k", tmp_path).load()
    assert set(back) == set(answers)
    for k, a in answers.items():
        assert np.array_equal(back[k].pose, a.pose) and back[k].payload == a.payload
        assert back[k].entropy_nats == a.entropy_nats
    (tmp_path / "k.npz").write_bytes(b"not a store")
    assert AnswerStore("k", tmp_path).load() == {}  # unreadable: computed again, no error


def test_the_key_changes_with_the_weights_the_drive_and_the_codec() -> None:
    cfg = replay_config(load(SMOKE))
    model = load_model(cfg.weights)
    drive = drive_of(cfg)
    key = answers_key(model, drive, cfg.codec)
    assert answers_key(model, drive, cfg.codec) == key
    assert answers_key(model, {**drive, "seed": drive["seed"] + 1}, cfg.codec) != key
    assert answers_key(model, drive, "fp32") != key
    other = LocNet()
    other.load_state_dict(model.state_dict())
    with torch.no_grad():
        next(other.parameters()).view(-1)[0] += 1e-6
    assert answers_key(other, drive, cfg.codec) != key


def test_the_cache_folder_follows_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("EDGELOC_CACHE_DIR", "/somewhere")
    assert cache_dir() == Path("/somewhere")
    monkeypatch.delenv("EDGELOC_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", "/xdg")
    assert cache_dir() == Path("/xdg/edgeloc-testbed")


def test_a_comparison_from_stored_answers_is_the_same_and_runs_no_dnn(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    scenario = load(SMOKE)
    cfg = replay_config(scenario)
    cfg = replace(cfg, duration_s=6.0, splits=cfg.splits[:2])
    ds, model = config_dataset(cfg), load_model(cfg.weights)
    latency = latency_model(scenario)
    store = AnswerStore(answers_key(model, drive_of(cfg), cfg.codec), tmp_path)
    first = compare_splits(cfg, latency, ds, model, InferenceCache(model, ds, cfg.codec))
    cold = InferenceCache(model, ds, cfg.codec)
    assert answer_all(cold, cfg.splits) == len(ds) * len(cfg.splits)
    assert answer_all(cold, cfg.splits) == 0  # whole now
    store.save(cold.answers())

    def no_dnn(*_: object) -> None:
        raise AssertionError("the DNN ran although every answer was stored")

    monkeypatch.setattr(LocNet, "vehicle_side", no_dnn)
    monkeypatch.setattr(ds, "image", no_dnn)  # nor was a frame rendered
    warm = InferenceCache(model, ds, cfg.codec)
    warm.remember(AnswerStore(store.key, tmp_path).load())
    assert compare_splits(cfg, latency, ds, model, warm).to_dict() == first.to_dict()
