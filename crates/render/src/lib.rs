//! `ic_render` — what a depth sensor would see.
//!
//! This crate will own headless depth + instance-mask rendering with wgpu (lavapipe when no GPU
//! is present), a CPU reference rasteriser with the same API, scene assembly (the object alone;
//! the object inside a textured cube room of side 4; distractors and a support plane), optional
//! sensor artefacts, and depth/mask image I/O (16-bit PNG with a BOP depth scale, 32-bit EXR).
//!
//! It depends on `ic_geometry` only and knows nothing about networks. See issue 3 and
//! `docs/ARCHITECTURE.md`.
