//! ICP refinement.
