//! Procrustes.
