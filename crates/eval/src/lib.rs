//! `ic_eval` — how accurate is a pose?
//!
//! This crate will own per-sample pose errors (rotation, translation, ADD, ADD-S, BOP MSSD and
//! MSPD), accuracy and mAP curves in the convention of Yi et al. 2018, markdown/JSON reports and
//! plots. It depends on `ic_geometry` only and knows nothing about networks. See issue 7.
