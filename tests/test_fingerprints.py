"""What the fingerprints of cached stages hash, against readable references: every key written by an earlier
version must still match (``array_digest`` hashes exactly the bytes of ``tobytes()``; the fit key's landmark
weights are the same numbers)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from capture.run.stages import landmark_weight_blocks, landmark_weights
from capture.run.store import Blocks, array_digest


def reference(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b"none")
            continue
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def test_digest_is_the_bytes_of_tobytes_without_copying_them():
    rng = np.random.default_rng(0)
    track = rng.normal(size=(6, 5, 2))
    cases = [
        (track,),
        (track[:, ::2], None, np.zeros(0)),                                 # strided: copied, same bytes
        (np.arange(7), rng.random((3, 3)) > 0.5, np.float32(2.0)),          # bool and a 0-d scalar
        (np.zeros((0, 468, 2)), np.asfortranarray(rng.normal(size=(3, 4)))),
        (track.astype(np.float32), track[0, 0, 0]),
    ]
    for case in cases:
        assert array_digest(*case) == reference(*case)
    assert len({array_digest(*c) for c in cases}) == len(cases)
    changed = track.copy()
    changed[3, 2, 1] = np.nextafter(changed[3, 2, 1], 1.0)
    assert array_digest(changed) != array_digest(track)


def test_landmark_weights_are_the_clipped_confidence_and_zero_where_missing():
    from types import SimpleNamespace

    rng = np.random.default_rng(1)
    points = rng.normal(size=(7, 5, 2))
    points[2, 1, 0] = np.nan
    points[4] = np.nan
    conf = rng.uniform(-0.5, 1.5, (7, 5))
    conf[3, 3] = np.nan
    conf[5, 0] = np.inf
    for c in (conf, None):
        w = np.ones(points.shape[:2]) if c is None else c
        ok = np.isfinite(points).all(-1) & np.isfinite(w)
        expected = np.where(ok, np.clip(w, 0.0, 1.0), 0.0)
        got = landmark_weights(SimpleNamespace(points=points, confidence=c))
        assert got.dtype == np.float64 and got.shape == (7, 5)
        assert got.tobytes() == expected.tobytes()
    assert landmark_weights(SimpleNamespace(points=points, confidence=conf))[5, 0] == 0.0
    assert conf[3, 3] != conf[3, 3]      # the track's own confidence is left alone


def test_blocks_hash_as_the_whole_array(monkeypatch):
    """The fit's key hashes the landmark weights block by block: the same digest as the whole (T, L) array,
    for a take shorter than a block, a whole number of blocks and a short last block."""
    from types import SimpleNamespace

    import capture.run.stages as stages

    monkeypatch.setattr(stages, "BLOCK_FRAMES", 4)
    rng = np.random.default_rng(2)
    for n in (0, 3, 8, 11):
        points = rng.normal(size=(n, 5, 2))
        points[::3, 1] = np.nan
        track = SimpleNamespace(points=points, confidence=rng.uniform(-0.2, 1.2, (n, 5)))
        whole = landmark_weights(track)
        assert array_digest(np.arange(n), landmark_weight_blocks(track)) == reference(np.arange(n), whole)
    with pytest.raises(ValueError, match="rows"):
        array_digest(Blocks(np.float64, (5, 2), lambda: [np.zeros((3, 2))]))
    with pytest.raises(ValueError, match="shape"):
        array_digest(Blocks(np.float64, (3, 2), lambda: [np.zeros((3, 4))]))


def test_landmark_checks_by_blocks_equal_the_whole(monkeypatch):
    import capture.run.checks as checks

    rng = np.random.default_rng(4)
    points = rng.normal(0, 30, size=(11, 12, 2))
    points[2] = 5.0                      # collapsed
    points[6, 3:] = np.nan               # too few landmarks
    conf = rng.uniform(0, 1, (11, 12))
    conf[9, 2:] = 0.0                    # too few confident ones
    whole = checks.landmark_problems(points, conf)
    assert [j for j, p in enumerate(whole) if p] == [2, 6, 9]
    monkeypatch.setattr(checks, "BLOCK_FRAMES", 4)
    assert list(checks.landmark_problems(points, conf)) == list(whole)
    assert list(checks.landmark_problems(points, None)) == list(checks._problems(points, None))
