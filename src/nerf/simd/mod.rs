//! The only home of `unsafe` and `std::arch`: AVX2+FMA kernels chosen at run
//! time with portable fallbacks.

pub mod grid;
