//! Layered exponential atmosphere (work in progress).
