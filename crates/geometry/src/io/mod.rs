//! Mesh and point-cloud file formats.
