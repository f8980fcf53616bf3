//! Steps 2-3 of the chain ([`super`] module docs: F, the projective frame, the
//! triangulation, the 3D homographies) on the captured pixels, fitted once per set of
//! inputs within one [`super::calibrate_rig`] call ([`ChainFits`]).
//!
//! What it keeps: a run of the chain without a lens start fits steps 2-3 from the rig
//! views (step 1 of the same views), `K0` (the image-size guess) and the estimation
//! options' F and 3D-homography RANSAC, fewest tracks and seed; the lens model does not
//! enter them (steps 1-4 treat the captured pixels as pinhole ones). With
//! [`super::LensChoice::Auto`] the chosen model's run repeats the radial-tangential run's
//! first estimate's steps 2-3 exactly; it takes them from here: the same inputs, the same
//! result, bit for bit. A run with a lens start fits its own (its pixels are undistorted
//! by its lens), or takes the lens grid's ([`super::two_pass::LensStart::fitted`]).
//!
//! Degrees of freedom and units: none estimated here; those of steps 2-3. Pitfalls: a
//! cache belongs to one list of views (its caller's); the key holds every option steps
//! 1-3 read, compared exactly. Failures are not kept: a failed fit runs again when asked
//! again, and sets its seeded report ([`super::Seeded`]) again.

use std::sync::{Arc, Mutex};

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::ransac::RansacOptions;

use super::CalibrateOptions;
use super::two_pass::GridFit;
use crate::error::AlignError;

/// What steps 1-3 on the captured pixels read besides the views (module docs).
#[derive(Debug, Clone, PartialEq)]
pub(super) struct FitKey {
    k0: Intrinsics,
    fundamental: RansacOptions,
    homography: RansacOptions,
    min_tracks: usize,
    seed: u64,
    planar_threshold_px: f64,
    planar_fraction: f64,
}

impl FitKey {
    /// The key of a run with `options` conditioned by `k0`.
    pub(super) fn of(options: &CalibrateOptions, k0: &Intrinsics) -> Self {
        let est = &options.estimation;
        Self {
            k0: *k0,
            fundamental: est.fundamental.clone(),
            homography: est.homography.clone(),
            min_tracks: est.min_tracks,
            seed: est.seed,
            planar_threshold_px: options.planar_threshold_px,
            planar_fraction: options.planar_fraction,
        }
    }
}

/// The steps 2-3 fitted so far on the captured pixels of one list of views, by key
/// (module docs).
#[derive(Default)]
pub(super) struct ChainFits(Mutex<Vec<(FitKey, Arc<GridFit>)>>);

impl ChainFits {
    /// The fit of `key`: the kept one, or `fit()`'s (kept when it succeeds).
    pub(super) fn get_or_fit(
        &self,
        key: FitKey,
        fit: impl FnOnce() -> Result<GridFit, AlignError>,
    ) -> Result<Arc<GridFit>, AlignError> {
        let kept = self.0.lock().ok().and_then(|k| k.iter().find(|(k, _)| *k == key).map(|(_, f)| f.clone()));
        if let Some(f) = kept {
            return Ok(f);
        }
        let f = Arc::new(fit()?);
        if let Ok(mut k) = self.0.lock() {
            k.push((key, f.clone()));
        }
        Ok(f)
    }
}
