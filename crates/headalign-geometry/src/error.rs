//! Typed errors of the geometry layer. Every estimator returns one of these instead of
//! panicking on degenerate or bad input.

use thiserror::Error;

/// What can go wrong in a geometric computation.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum GeometryError {
    /// Fewer data than the computation needs.
    #[error("not enough data: need at least {needed}, got {got} ({what})")]
    NotEnoughData {
        /// What was being counted.
        what: &'static str,
        /// Minimum required.
        needed: usize,
        /// Number available.
        got: usize,
    },
    /// The configuration of the data makes the problem ill posed (e.g. collinear points,
    /// rotations about one axis).
    #[error("degenerate configuration: {0}")]
    Degenerate(String),
    /// A numerical routine (SVD, eigen-decomposition, Cholesky) failed or did not converge.
    #[error("numerical failure: {0}")]
    Numerical(String),
    /// RANSAC found no model with enough support.
    #[error("robust estimation failed: {0}")]
    NoConsensus(String),
    /// An estimate exists but is not of the required kind (e.g. a 3D homography that is
    /// not conjugate to a rigid motion, a dual conic that is not positive definite).
    #[error("invalid estimate: {0}")]
    InvalidEstimate(String),
    /// Options that fail `validate()`.
    #[error("invalid option: {0}")]
    InvalidOption(String),
}
