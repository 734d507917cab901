//! # vdd-data
//!
//! Demonstration datasets: episodes, windows and chunks, normalisation, npy/npz IO.
#![warn(missing_docs)]
