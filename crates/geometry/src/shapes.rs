//! Procedural shapes.
