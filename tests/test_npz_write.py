"""capture.io.arrays.write_npz: the same arrays as np.savez, read back by np.load and the checked reader."""

from __future__ import annotations

import numpy as np
import pytest

from capture.io.arrays import load_npz, write_npz


def _arrays():
    rng = np.random.default_rng(0)
    return {
        "stacked": [rng.normal(size=(4, 3)).astype(np.float32) for _ in range(7)],   # rows written as their stack
        "plain": rng.normal(size=(5, 4, 3)),
        "fortran": np.asfortranarray(rng.normal(size=(3, 4))),                       # written in C order
        "strided": rng.normal(size=(6, 4))[:, ::2],
        "strings": np.array(["fitted", "bridged"]),
        "scalar": np.float64(3.5),
        "empty": np.zeros((0, 2)),
        "empty_rows": [np.zeros((0, 3)), np.zeros((0, 3))],
        "ints": np.arange(12, dtype=np.int64).reshape(3, 4),
    }


def test_reads_back_as_np_savez_would(tmp_path):
    arrays = _arrays()
    with open(tmp_path / "ours.npz", "wb") as fh:
        write_npz(fh, arrays)
    np.savez(tmp_path / "numpy.npz", **{k: np.stack(v) if isinstance(v, list) else v for k, v in arrays.items()})
    ours, ref = np.load(tmp_path / "ours.npz"), np.load(tmp_path / "numpy.npz")
    checked = load_npz(tmp_path / "ours.npz", "test archive", "write it again")
    assert sorted(ours.files) == sorted(ref.files) == sorted(arrays)
    for k in arrays:
        for got in (ours[k], checked[k]):
            assert got.dtype == ref[k].dtype and got.shape == ref[k].shape, k
            np.testing.assert_array_equal(got, ref[k])


def test_refuses_rows_that_differ_and_objects(tmp_path):
    with open(tmp_path / "a.npz", "wb") as fh, pytest.raises(ValueError, match="different shapes or types"):
        write_npz(fh, {"x": [np.zeros(3), np.zeros(4)]})
    with open(tmp_path / "b.npz", "wb") as fh, pytest.raises(ValueError, match="different shapes or types"):
        write_npz(fh, {"x": [np.zeros(3), np.zeros(3, np.float32)]})
    with open(tmp_path / "c.npz", "wb") as fh, pytest.raises(ValueError, match="object"):
        write_npz(fh, {"x": np.array([{}, None], dtype=object)})
    with open(tmp_path / "d.npz", "wb") as fh, pytest.raises(ValueError, match="no rows"):
        write_npz(fh, {"x": []})


def test_deflated_members_read_back_and_only_those_are_compressed(tmp_path):
    """``deflate`` compresses just the named members (what params.npz does with coefficients repeated per
    landmark): np.load reads the same arrays, the file shrinks, and the checked cache reader refuses it."""
    import zipfile

    rng = np.random.default_rng(1)
    rows = rng.normal(size=(50, 1, 24)).astype(np.float32)
    arrays = {"repeated": np.ascontiguousarray(np.broadcast_to(rows, (50, 468, 24))), "noise": rng.normal(size=(50, 3))}
    with open(tmp_path / "plain.npz", "wb") as fh:
        write_npz(fh, arrays)
    with open(tmp_path / "deflated.npz", "wb") as fh:
        write_npz(fh, arrays, deflate=["repeated"])
    with zipfile.ZipFile(tmp_path / "deflated.npz") as z:
        kinds = {i.filename: i.compress_type for i in z.infolist()}
    assert kinds == {"repeated.npy": zipfile.ZIP_DEFLATED, "noise.npy": zipfile.ZIP_STORED}
    assert (tmp_path / "deflated.npz").stat().st_size < (tmp_path / "plain.npz").stat().st_size / 20
    with np.load(tmp_path / "deflated.npz", allow_pickle=False) as z:
        for k, v in arrays.items():
            assert z[k].dtype == v.dtype
            np.testing.assert_array_equal(z[k], v)
    with pytest.raises(Exception, match="compressed"):
        load_npz(tmp_path / "deflated.npz", "test archive", "write it again")
