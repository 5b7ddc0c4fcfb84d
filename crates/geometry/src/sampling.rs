//! Surface sampling.
