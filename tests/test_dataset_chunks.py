"""The sensor files' gzip datasets compressed on threads (`twin.dataset._GzipChunks`) read back, through h5py's own
gzip filter, as the arrays written: several chunks with a partial last one, rows larger than a chunk, booleans,
integers, one-dimensional arrays, scalars and empty arrays."""

from pathlib import Path

import h5py
import numpy as np

from twin.dataset import CHUNK_BYTES, _GzipChunks


def test_threaded_gzip_datasets_read_back_exactly(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    arrays = {
        "rows": rng.standard_normal((3 * CHUNK_BYTES // (40 * 3 * 8) + 7, 40, 3)),  # 4 chunks, the last partial
        "wide": rng.standard_normal((5, CHUNK_BYTES // 8 + 11)),  # a row larger than a chunk: a row per chunk
        "counts": rng.integers(0, 4096, (20_000, 19)).astype(np.int32),
        "flags": rng.random(300_000) < 0.3,
        "line": np.cumsum(rng.standard_normal(200_000)),
        "scalar": np.float64(2.5),
        "empty": np.zeros((0, 3)),
    }
    path = tmp_path / "chunks.h5"
    with h5py.File(path, "w") as f, _GzipChunks(workers=3) as chunks:
        for name, data in arrays.items():
            chunks.create(f.create_group(name), "data", data)
    with h5py.File(path, "r") as f:
        for name, data in arrays.items():
            dataset = f[f"{name}/data"]
            assert dataset.dtype == np.asarray(data).dtype, name
            np.testing.assert_array_equal(dataset[()], data, err_msg=name)
            if np.ndim(data) and np.size(data):
                assert dataset.compression == "gzip" and dataset.compression_opts == 1, name
        assert f["rows/data"].chunks[0] * 40 * 3 * 8 <= CHUNK_BYTES
    plain = tmp_path / "plain.h5"  # h5py's own filter, one chunk at a time: a file of about the same size
    with h5py.File(plain, "w") as f:
        for name, data in arrays.items():
            if np.ndim(data) and np.size(data):
                f.create_dataset(f"{name}/data", data=data, compression="gzip", compression_opts=1)
    assert path.stat().st_size < 1.2 * plain.stat().st_size
