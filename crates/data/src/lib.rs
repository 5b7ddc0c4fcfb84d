//! `ic_data` — samples for training and testing, exactly as the paper builds them.
//!
//! This crate will own object corpora and splits (ModelNet40 `<class>/{train,test}/*.off`, a flat
//! folder of meshes split by id range or split file, BOP `models/`, procedural objects), seeded
//! sample generation (object alone, object in the room), ground-truth assignments with outlier
//! bins, a prefetching batch iterator, BOP dataset reading/writing and registration-case export.
//!
//! It depends on `ic_geometry` and `ic_render` and knows nothing about networks. See issue 4.
