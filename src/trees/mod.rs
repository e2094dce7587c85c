//! 3D tree reconstruction from waveform points (Wu 2012, chapter 4): stems and first-order
//! branches as cylinders, from the georeferenced samples above an intensity threshold.
//!
//! - `points.rs`: the input, the hyper point cloud a replay writes (`hyper_points.las`).
//! - `reconstruct.rs`: ground, optimal threshold, foliage filter, trees, stem, DBSCAN of the
//!   branches, a cylinder per branch reconnected to the stem.
//! - `cluster.rs`: DBSCAN (`petal-clustering`) and ball-tree neighbours (`petal-neighbors`).
//! - `cylinder.rs`: the cylinder and the line fit.
//! - `score.rs`: the score against the simulator's trees and branches.
//! - `output.rs`: `cylinders.csv`, `cylinders.ply`, `clustered_points.las`, the threshold curve,
//!   `scores.csv`.
//!
//! `fwlidar trees` (`cli/trees.rs`) runs it; `docs/trees.md` describes method and outputs.

pub mod cluster;
pub mod cylinder;
pub mod output;
pub mod points;
pub mod reconstruct;
pub mod score;

pub use reconstruct::{Reconstruction, Threshold, TreesOptions, reconstruct};

/// Why tree reconstruction failed.
#[derive(Debug, thiserror::Error)]
pub enum TreesError {
    /// The point file is unreadable or malformed.
    #[error("{path}: {field}: {why}")]
    Points {
        /// The file.
        path: String,
        /// The field at fault.
        field: String,
        /// What is wrong.
        why: String,
    },
    /// A truth file is unreadable or malformed.
    #[error("{path}: {why}")]
    Truth {
        /// The file.
        path: String,
        /// What is wrong.
        why: String,
    },
    /// The points cannot give trees.
    #[error("{0}")]
    Input(String),
    /// An output could not be written.
    #[error("cannot write {path}: {why}")]
    Write {
        /// The file.
        path: String,
        /// Why.
        why: String,
    },
}
