//! SIMD kernels for the hash grid.
