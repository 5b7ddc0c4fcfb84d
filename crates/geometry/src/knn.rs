//! kNN.
