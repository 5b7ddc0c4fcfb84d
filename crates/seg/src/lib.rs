//! `ic_seg` — finds the object in the depth map.
//!
//! This crate will own the depth-only instance-mask network (a compact candle encoder–decoder
//! standing in for the paper's YOLACT), its training step, the paper's mask post-processing
//! (threshold, components, best instance, 3×3 erosion, 1.2-radius crop) and a geometry-only
//! alternative (RANSAC plane removal + Euclidean clustering). It knows nothing about pose. See
//! issue 6.
