//! Multi-resolution hash encoding.
