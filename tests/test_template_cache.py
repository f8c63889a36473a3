"""The actor's networks at its template, cached in the user's cache (``capture.actor.template_cache``):
read back bit for bit without evaluating the networks, keyed by the weights, and never in the way when the
cache is broken or cannot be written."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.tiny_actor import train_tiny_actor

FIELDS = ("bone", "thickness", "normal", "neutral", "skin_weight", "expressions")


@pytest.fixture(scope="module")
def actor_dir(tmp_path_factory):
    return train_tiny_actor(tmp_path_factory.mktemp("tcache"), iterations=20)


def _evaluated(actor):
    with torch.no_grad():
        return actor.model(torch.as_tensor(actor.template_vertices, dtype=torch.float32))


def _assert_same(a, b):
    for f in FIELDS:
        assert torch.equal(getattr(a, f), getattr(b, f)), f


def test_the_first_evaluation_is_read_back_without_running_the_networks(actor_dir, tmp_path, monkeypatch):
    from capture.actor import template_cache
    from capture.actor.package import load_actor

    monkeypatch.setenv("CAPTURE_CACHE", str(tmp_path / "cache"))
    first = load_actor(str(actor_dir)).at_template()
    files = list((tmp_path / "cache" / template_cache.SUBDIR).glob("*.safetensors"))
    assert len(files) == 1
    again = load_actor(str(actor_dir))
    monkeypatch.setattr(type(again.model), "forward", lambda *a, **k: pytest.fail("the networks ran"))
    _assert_same(again.at_template(), first)
    monkeypatch.undo()
    _assert_same(first, _evaluated(load_actor(str(actor_dir))))   # what was cached is the evaluation
    assert not list(actor_dir.glob("at_template*"))                # the package is not written


def test_a_broken_or_unwritable_cache_falls_back_to_evaluating(actor_dir, tmp_path, monkeypatch):
    from capture.actor import template_cache
    from capture.actor.package import load_actor

    ref = _evaluated(load_actor(str(actor_dir)))
    monkeypatch.setenv("CAPTURE_CACHE", str(tmp_path / "cache"))
    load_actor(str(actor_dir)).at_template()
    path, = (tmp_path / "cache" / template_cache.SUBDIR).glob("*.safetensors")
    path.write_bytes(b"not a safetensors file")
    _assert_same(load_actor(str(actor_dir)).at_template(), ref)     # evaluated again ...
    _assert_same(template_cache.read(path.stem, "cpu"), ref)       # ... and written again
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    monkeypatch.setenv("CAPTURE_CACHE", str(blocker))               # mkdir below a file fails
    _assert_same(load_actor(str(actor_dir)).at_template(), ref)


def test_the_key_follows_the_weights_the_template_and_the_configuration():
    from capture.actor.template_cache import cache_key

    rng = np.random.default_rng(0)
    w = {"model.a": rng.normal(size=(4, 3)).astype(np.float32), "jaw_t": np.zeros((2, 3), np.float32)}
    tv = rng.normal(size=(5, 3))
    cfg = {"width": 64}
    k = cache_key(cfg, tv, w)
    assert k == cache_key(cfg, tv.copy(), {n: v.copy() for n, v in reversed(w.items())})
    w2 = {**w, "model.a": w["model.a"].copy()}
    w2["model.a"][1, 2] = np.nextafter(w2["model.a"][1, 2], np.float32(1))   # one weight, one ulp
    tv2 = tv.copy()
    tv2[3, 0] += 1e-9
    assert len({k, cache_key(cfg, tv, w2), cache_key(cfg, tv2, w), cache_key({"width": 128}, tv, w)}) == 4
