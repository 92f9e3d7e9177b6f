"""Double-precision warp types shared by the FE kernels (Newton needs float64 accuracy)."""

import warp as wp

# Keep warp's start-up banner and module-load messages off stdout (the CLI prints JSON there).
wp.config.log_level = wp.LOG_WARNING

mat32d = wp.types.matrix(shape=(3, 2), dtype=wp.float64)
mat99d = wp.types.matrix(shape=(9, 9), dtype=wp.float64)
vec9d = wp.types.vector(length=9, dtype=wp.float64)
vec12d = wp.types.vector(length=12, dtype=wp.float64)
mat1818d = wp.types.matrix(shape=(18, 18), dtype=wp.float64)
vec6i = wp.types.vector(length=6, dtype=wp.int32)
