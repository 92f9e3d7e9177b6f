"""Writing a sensor file's largest kind of dataset: h5py's gzip filter (one chunk at a time) against
`twin.dataset._GzipChunks` (chunks deflated on threads), same data, same level, in one process.

    python benchmarks/gzip_bench.py [--rows 1500] [--vertices 4000] [--workers N]

The data are (rows, vertices, 3) float64 random walks along the rows, like the `nodal_res` rows of a 0.5 mm-mesh
campaign (~4000 vertices). On a machine whose cores are busy the threads gain nothing; the campaign's 16-core GPU
machines are where they matter (docs/scale.md).
"""

import argparse
import os
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
from rich.console import Console
from rich.table import Table

from twin.dataset import _GzipChunks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, default=1500)
    parser.add_argument("--vertices", type=int, default=4000)
    parser.add_argument("--workers", type=int, default=None, help="threads (default: min(8, cores))")
    args = parser.parse_args()
    steps = np.random.default_rng(0).standard_normal((args.rows, args.vertices, 3)) * 1e-6
    data = np.cumsum(steps, axis=0)
    table = Table(title=f"gzip level 1 of a {data.nbytes / 1e6:.0f} MB array, {os.cpu_count()} cores")
    for column in ("writer", "wall (s)", "file (MB)", "vs h5py filter"):
        table.add_column(column, justify="left" if column == "writer" else "right")
    with tempfile.TemporaryDirectory() as folder:
        walls = {}
        for name in ("h5py filter", "threads"):
            path = Path(folder) / f"{name}.h5"
            start = time.perf_counter()
            with h5py.File(path, "w") as f:
                if name == "threads":
                    with _GzipChunks(args.workers) as chunks:
                        chunks.create(f, "d", data)
                else:
                    f.create_dataset("d", data=data, compression="gzip", compression_opts=1)
            walls[name] = time.perf_counter() - start
            ratio = walls[name] / walls["h5py filter"]
            table.add_row(name, f"{walls[name]:.2f}", f"{path.stat().st_size / 1e6:.0f}", f"{ratio:.2f}")
    Console(width=100).print(table)


if __name__ == "__main__":
    main()
