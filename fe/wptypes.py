"""Double-precision warp types shared by the FE kernels (Newton needs float64 accuracy), launches by argument
name, and warp's set-up.

Where no NVIDIA CUDA driver can be loaded, warp is initialised here, on import, without the line its native
library prints straight to stderr ("Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"): a
CPU machine stays quiet, and asking for a CUDA device there fails with the device check's own message.
"""

import ctypes
import os
import sys
import tempfile

import warp as wp

# Keep warp's start-up banner and module-load messages off stdout (the CLI prints JSON there).
wp.config.log_level = wp.LOG_WARNING

_NO_DRIVER_LINE = "Could not find or load the NVIDIA CUDA driver"
_DRIVER_LIBRARIES = {"linux": ("libcuda.so", "libcuda.so.1"), "win32": ("nvcuda.dll",)}


def _cuda_driver_loadable() -> bool:
    """Whether a CUDA driver library that warp looks for loads in this process."""
    for name in _DRIVER_LIBRARIES.get(sys.platform, ()):
        try:
            ctypes.CDLL(name)
        except OSError:
            continue
        return True
    return False


def _init_without_driver_warning() -> None:
    """``wp.init()`` with file descriptor 2 captured; everything but the no-driver line is written back."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            wp.init()
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        lines = captured.read().decode(errors="replace").splitlines(keepends=True)
    sys.stderr.write("".join(line for line in lines if _NO_DRIVER_LINE not in line))


if not _cuda_driver_loadable():
    _init_without_driver_warning()


def host_device() -> str:
    """The warp device for a model's own solves (inflation): "cpu" where warp can compile CPU kernels, else
    the default CUDA device (a GPU machine whose warp ships without its CPU compiler)."""
    return "cpu" if wp.is_cpu_available() else "cuda"


mat32d = wp.types.matrix(shape=(3, 2), dtype=wp.float64)
mat99d = wp.types.matrix(shape=(9, 9), dtype=wp.float64)
vec12d = wp.types.vector(length=12, dtype=wp.float64)
mat1818d = wp.types.matrix(shape=(18, 18), dtype=wp.float64)
vec6i = wp.types.vector(length=6, dtype=wp.int32)


@wp.func
def add_block(H: mat99d, a: int, b: int, m: wp.mat33d) -> mat99d:
    """H with m added to its 3x3 block (a, b): rows of node a, columns of node b of a triangle."""
    for i in range(3):
        for j in range(3):
            H[3 * a + i, 3 * b + j] += m[i, j]
    return H


def launch(kernel: wp.Kernel, dim: int | tuple, values: dict, device: str) -> None:
    """Launch `kernel` taking its arguments by name from `values` (robust to argument order; other entries are
    ignored); a kernel argument missing from `values` is an error naming it."""
    names = [arg.label for arg in kernel.adj.args]
    missing = [n for n in names if n not in values]
    if missing:
        raise RuntimeError(f"kernel {kernel.key} takes {missing}, which its caller does not provide")
    wp.launch(kernel, dim, [values[n] for n in names], device=device)
