//! Step 4 of the estimation ([`super`]): the 3D homography of each rotated rig view
//! (paper section 3.2 steps 2-4(c); `docs/how-it-works.md#the-3d-homography-of-a-rotation`).
//!
//! A rotation of the head maps the reference view's projective points `X` to the rotated
//! view's `Y ~ H X`, `H = H_PE^-1 D H_PE` a 4x4 projective map (15 dof as estimated),
//! conjugate by the frame's `H_PE` to the rigid motion `D` (6 dof; paper equation 1). The
//! matches between the two stereo views give quadruplets (left and right pixel in each
//! view) with their points `X`, `Y`. Per view:
//! 1. the quadruplets are screened by 4-point plane-homography RANSAC on left0 -> left1
//!    and right0 -> right1 ([`screen_rotation`]): a head rotation maps each image almost
//!    by `K R K^-1`, departing from it only by the parallax of the axis offsets (threshold
//!    [`super::EstimationOptions::prefilter_px`]); the plane homographies are kept for the
//!    rotating-camera start ([`super::starts`]);
//! 2. starting models: the rigid fit in the quasi-Euclidean frame and the DLT over the
//!    screened set, each polished by Levenberg-Marquardt on the symmetric transfer
//!    error ([`polish`]); the 5-point DLT RANSAC ([`PolishedHomography`]) runs only when
//!    neither explains half of the screened set;
//! 3. guided re-selection over all quadruplets with the polished `H`, refitted, until the
//!    inlier set stops changing (paper 4(b)-(c));
//! 4. `H` scaled to determinant 1; one without a complex eigenvalue pair blocks the linear
//!    chain (its invariant line is what that start needs) but not the other starts.
//!
//! Units: symmetric transfer error in pixels, the RMS over the four images of a
//! quadruplet ([`headalign_geometry::homography3d::symmetric_transfer_error`]), threshold
//! [`super::EstimationOptions::homography`]. Pitfalls: with a 3 deg rotation `H` is close
//! to the identity, and the algebraic DLT over many noisy points can come out
//! near-singular or with `det H <= 0` (no scaling makes that a rigid conjugate: such models
//! are dropped); the DLT over-weights far points, whose triangulated depth is poor, hence
//! the polish on transfer error. A view whose homography fails is named by the caller
//! ([`super::estimate_rig`] can leave it out).
//!
//! Without quadruplets ([`HomographyMode::Optional`], the fallback of
//! [`super::EstimationOptions::views_without_homography`]): with a fraction `e` of wrong
//! observations only `(1 - e)^4` of the tracks are right in all four images of a rotation
//! (1/16 at 50 %, 1/39 at 60 %: some 5 of 200 points, fewer than a 3D homography's
//! sample), while `(1 - e)^2` are right in one camera's image pair. A view whose 3D
//! homography fails then keeps its place and its observations; it only takes the
//! linear start away (that start needs every rotation's `H`). The plane homographies of
//! every rotation come from the image pairs of the tracks reconstructed in either of the
//! two views (`(1 - e)` of them right, not `(1 - e)^4`; [`plane_rotations`]), so that the
//! rotating-camera start still gets its intrinsics.

use headalign_geometry::camera::ProjectiveCamera;
use headalign_geometry::homography2d::Homography2Estimator;
use headalign_geometry::homography3d::{
    Homography3, Homography3Estimator, Quadruplet, TransferModel, refine_transfer, symmetric_transfer_error,
};
use headalign_geometry::ransac::{Estimator, RansacOptions, ransac};
use headalign_geometry::registration::RigidFrameEstimator;
use nalgebra::{Matrix3, Point2};

use super::frame::{ProjectiveStructure, Reconstruction};
use super::{DroppedView, EstimationOptions, HomographyReport};
use crate::error::{AlignError, StepContext};
use crate::observations::View;
use crate::rig::stereo::rms;

/// The plane homographies (left, right) of one rotation.
pub(super) type PlanePair = (Matrix3<f64>, Matrix3<f64>);

/// The 3D homographies of the rotated rig views ([`rotation_homographies`]).
pub(super) struct RotationHomographies {
    /// Diagnostics, one per rotated view.
    pub reports: Vec<HomographyReport>,
    /// Each rotated view's `H`, scaled to determinant 1.
    pub homographies: Vec<Homography3>,
    /// Why the linear start cannot run (a 3D homography without a rotation's
    /// eigenvalues), if it cannot.
    pub linear_blocked: Option<AlignError>,
    /// Per rig view (the reference view's empty), the tracks of the quadruplet inliers,
    /// sorted.
    pub quad_inliers: Vec<Vec<u64>>,
    /// Plane homographies (left, right) of each rotation whose screening found both, for
    /// the rotation-based start.
    pub image_rotations: Vec<PlanePair>,
    /// The rotated views without a 3D homography ([`HomographyMode::Optional`]), with the
    /// error of their fit.
    pub without_homography: Vec<DroppedView>,
}

/// Whether every rotated view must have its 3D homography.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum HomographyMode {
    /// A view whose 3D homography fails is an error (named by `at_view`).
    Required,
    /// A view whose 3D homography fails is listed in
    /// [`RotationHomographies::without_homography`] and blocks the linear start; the
    /// plane homographies come from the wider pair set of [`plane_rotations`].
    Optional,
}

/// The 3D homography of every rotated rig view (`rig[1..]`, indices into `views`) against
/// the reference view `rig[0]`. While a view is being fitted `at_view` names it (index
/// into `views`), so that an error can be traced to it; `None` once all are fitted. With
/// [`HomographyMode::Optional`] a view's failure is recorded instead (module docs).
pub(super) fn rotation_homographies(
    views: &[View],
    rig: &[usize],
    structure: &ProjectiveStructure,
    options: &EstimationOptions,
    mode: HomographyMode,
    at_view: &mut Option<usize>,
) -> Result<RotationHomographies, AlignError> {
    let (p_l, p_r, recon) = (&structure.p_l, &structure.p_r, &structure.recon);
    let estimator = Homography3Estimator { p_left: *p_l, p_right: *p_r };
    let mut h_reports = Vec::new();
    let mut homographies = Vec::new();
    let mut linear_blocked: Option<AlignError> = None;
    let mut quad_inliers: Vec<Vec<u64>> = vec![Vec::new(); rig.len()];
    let mut image_rotations: Vec<PlanePair> = Vec::new();
    let mut without_homography = Vec::new();
    for (slot, &vi) in rig.iter().enumerate().skip(1) {
        *at_view = Some(vi);
        let pairs = (&recon[0], &recon[slot]);
        let fit = match mode {
            HomographyMode::Required => {
                view_homography(views, vi, pairs, &estimator, options, &mut image_rotations)?
            }
            HomographyMode::Optional => {
                if let Some(g) = plane_rotations(&views[rig[0]], &views[vi], pairs, options) {
                    image_rotations.push(g);
                }
                match view_homography(views, vi, pairs, &estimator, options, &mut Vec::new()) {
                    Ok(fit) => fit,
                    Err(e) => {
                        if linear_blocked.is_none() {
                            linear_blocked = Some(AlignError::NotARotation {
                                view: views[vi].name.clone(),
                                why: format!("no 3D homography ({e})"),
                            });
                        }
                        without_homography
                            .push(DroppedView { view: views[vi].name.clone(), reason: e.to_string() });
                        continue;
                    }
                }
            }
        };
        h_reports.push(fit.report);
        let h = fit.h;
        // A noisy 3D homography of a small rotation (50 points at 1.5 px in a scene about
        // 1 m away: 3 of 60 trials) can lose its complex eigenvalue pair. Only the linear
        // chain needs its eigenvectors: that start is then skipped with this reason, and
        // the other starts (image homographies, calibrated pose, rough) still run.
        if linear_blocked.is_none() && headalign_geometry::invariant::invariant_points(&h.0).is_err() {
            linear_blocked = Some(AlignError::NotARotation {
                view: views[vi].name.clone(),
                why: "its 3D homography has no complex eigenvalue pair (no measurable rotation)".into(),
            });
        }
        homographies.push(h);
        quad_inliers[slot] = fit.inlier_tracks;
    }
    *at_view = None;
    Ok(RotationHomographies {
        reports: h_reports,
        homographies,
        linear_blocked,
        quad_inliers,
        image_rotations,
        without_homography,
    })
}

/// One rotated view's fit ([`view_homography`]).
struct ViewHomography {
    report: HomographyReport,
    /// `H` scaled to determinant 1.
    h: Homography3,
    /// Tracks of the inlier quadruplets, sorted.
    inlier_tracks: Vec<u64>,
}

/// The 3D homography of view `vi` from the reference and rotated reconstructions
/// `(recon0, recon1)`: quadruplets, plane-homography screening (the plane pair, if both
/// were found, pushed to `image_rotations`), starting model, guided re-selection (module
/// docs). Too few quadruplets at any stage is [`AlignError::TooFewTracks`].
fn view_homography(
    views: &[View],
    vi: usize,
    (recon0, recon1): (&Reconstruction, &Reconstruction),
    estimator: &Homography3Estimator,
    options: &EstimationOptions,
    image_rotations: &mut Vec<PlanePair>,
) -> Result<ViewHomography, AlignError> {
    let (p_l, p_r) = (&estimator.p_left, &estimator.p_right);
    let (tracks, quads) = quadruplets(recon0, recon1);
    if quads.len() < options.min_tracks {
        return Err(AlignError::TooFewTracks {
            what: format!("seen in both stereo views '{}' and '{}'", views[0].name, views[vi].name),
            needed: options.min_tracks,
            got: quads.len(),
        });
    }
    let opts = RansacOptions { seed: options.seed.wrapping_add(vi as u64), ..options.homography };
    // Consensus: a head rotation maps each camera's image almost by K R K^-1, so
    // quadruplets are first screened by 4-point plane-homography RANSAC on
    // left0 -> left1 and right0 -> right1 (robust); then the 5-point 3D DLT RANSAC
    // (polished on transfer error) runs on the screened set, and guided re-selection
    // over all quadruplets with the 3D homography repeats until the set is stable.
    let (screened, plane_homographies) = screen_rotation(&quads, options.prefilter_px, opts.seed);
    if let Some(g) = plane_homographies {
        image_rotations.push(g);
    }
    if screened.len() < options.min_tracks {
        return Err(AlignError::TooFewTracks {
            what: format!("consistent with a rotation between '{}' and '{}'", views[0].name, views[vi].name),
            needed: options.min_tracks,
            got: screened.len(),
        });
    }
    let hview = format!("3D homography for view '{}'", views[vi].name);
    let (best, ransac_iterations) = start_model(&quads, &screened, estimator, &opts, &hview)?;
    let Some((model, _)) = best else {
        return Err(AlignError::NotARotation {
            view: views[vi].name.clone(),
            why: "no 3D homography fits its matches".into(),
        });
    };
    let (model, inliers, rounds) = guided_reselection(model, &quads, p_l, p_r, options.homography.threshold);
    if inliers.len() < options.min_tracks {
        return Err(AlignError::TooFewTracks {
            what: format!("fitting the 3D homography of view '{}'", views[vi].name),
            needed: options.min_tracks,
            got: inliers.len(),
        });
    }
    let rms_t = rms(inliers.iter().map(|&i| symmetric_transfer_error(&model, p_l, p_r, &quads[i])));
    let report = HomographyReport {
        view: views[vi].name.clone(),
        candidates: quads.len(),
        inliers: inliers.len(),
        ransac_iterations,
        guided_rounds: rounds,
        rms_transfer_px: rms_t,
    };
    let h = model.h.normalized_det().map_err(|e| AlignError::NotARotation {
        view: views[vi].name.clone(),
        why: format!("its 3D homography {e}"),
    })?;
    Ok(ViewHomography { report, h, inlier_tracks: inliers.iter().map(|&i| tracks[i]).collect() })
}

/// The quadruplets of the tracks reconstructed in both views (reference `recon0`, rotated
/// `recon1`), in track order, with their tracks.
fn quadruplets(recon0: &Reconstruction, recon1: &Reconstruction) -> (Vec<u64>, Vec<Quadruplet>) {
    let mut tracks = Vec::new();
    let mut quads = Vec::new();
    for (track, (x, l0, r0)) in recon0 {
        if let Some((y, l1, r1)) = recon1.get(track) {
            tracks.push(*track);
            quads.push(Quadruplet { x: *x, y: *y, left0: *l0, right0: *r0, left1: *l1, right1: *r1 });
        }
    }
    (tracks, quads)
}

/// The starting model of a view's 3D homography and its support (quadruplets within
/// `ransac_options.threshold` of transfer error), with the iterations of the fallback
/// RANSAC (0 when it did not run). `None` when no model fits; an error of the fallback
/// RANSAC is reported under `step`.
fn start_model(
    quads: &[Quadruplet],
    screened: &[usize],
    estimator: &Homography3Estimator,
    ransac_options: &RansacOptions,
    step: &str,
) -> Result<(Option<(TransferModel, usize)>, usize), AlignError> {
    let (p_l, p_r) = (estimator.p_left, estimator.p_right);
    let count = |m: &TransferModel| {
        quads
            .iter()
            .filter(|q| symmetric_transfer_error(m, &p_l, &p_r, q) <= ransac_options.threshold)
            .count()
    };
    // Starting models: the rigid fit in the quasi-Euclidean frame (always well
    // conditioned, a few pixels biased) and the DLT when it is a valid rigid conjugate
    // (with a 3 deg rotation H is close to the identity and the DLT over many noisy
    // points can come out near-singular); each is polished on transfer error.
    let rigid = RigidFrameEstimator { p_left: p_l, p_right: p_r };
    let mut best: Option<(TransferModel, usize)> = None;
    for start in
        [rigid.fit_inliers(quads, screened), estimator.fit_inliers(quads, screened)].into_iter().flatten()
    {
        if start.h.0.determinant() <= 0.0 {
            continue;
        }
        let Some(m) = polish(&start, quads, screened, &p_l, &p_r) else { continue };
        let n = count(&m);
        if best.as_ref().is_none_or(|(_, b)| n > *b) {
            best = Some((m, n));
        }
    }
    let mut ransac_iterations = 0;
    // Fallback: the 5-point DLT RANSAC with polished local optimisation.
    if best.as_ref().is_none_or(|(_, n)| *n * 2 < screened.len()) {
        let screened_quads: Vec<Quadruplet> = screened.iter().map(|&i| quads[i]).collect();
        let rep = ransac(&PolishedHomography(estimator), &screened_quads, ransac_options).step(step)?;
        ransac_iterations = rep.iterations;
        let n = count(&rep.model);
        if best.as_ref().is_none_or(|(_, b)| n > *b) {
            best = Some((rep.model, n));
        }
    }
    Ok((best, ransac_iterations))
}

/// Rounds of guided re-selection at most (module docs).
pub(crate) const GUIDED_ROUNDS: usize = 10;

/// Guided re-selection (paper section 3.2 step 4(b)-(c);
/// [`headalign_geometry::ransac::guided_reselection`]): the quadruplets within
/// `threshold_px` of transfer error under `model`, the model polished on them, repeated
/// (at most [`GUIDED_ROUNDS`] rounds) until the set is stable or would shrink. Returns the
/// model, its inlier indices and the rounds run.
pub(crate) fn guided_reselection(
    model: TransferModel,
    quads: &[Quadruplet],
    p_l: &ProjectiveCamera,
    p_r: &ProjectiveCamera,
    threshold_px: f64,
) -> (TransferModel, Vec<usize>, usize) {
    let select = |m: &TransferModel| -> Vec<usize> {
        (0..quads.len())
            .filter(|&i| symmetric_transfer_error(m, p_l, p_r, &quads[i]) <= threshold_px)
            .collect()
    };
    let refit = |m: &TransferModel, inliers: &[usize]| polish(m, quads, inliers, p_l, p_r);
    headalign_geometry::ransac::guided_reselection(model, GUIDED_ROUNDS, select, refit)
}

/// RANSAC adapter for 3D homographies whose least-squares fit (used by local
/// optimisation and the guided loop) is the DLT polished by Levenberg-Marquardt on
/// transfer error: the algebraic DLT over-weights far points, whose triangulated depth is
/// poor, and under 1 px noise its consensus is only about half the true inliers.
pub(crate) struct PolishedHomography<'a>(pub(crate) &'a Homography3Estimator);

impl Estimator for PolishedHomography<'_> {
    type Datum = Quadruplet;
    type Model = TransferModel;

    fn sample_size(&self) -> usize {
        self.0.sample_size()
    }

    /// Minimal DLT models with `det H <= 0` are dropped: `det(lambda H) = lambda^4 det H`,
    /// so no scaling makes them conjugate to a rigid motion.
    fn fit_minimal(&self, data: &[Quadruplet], sample: &[usize]) -> Vec<TransferModel> {
        let mut models = self.0.fit_minimal(data, sample);
        models.retain(|m| m.h.0.determinant() > 0.0);
        models
    }

    fn fit_inliers(&self, data: &[Quadruplet], inliers: &[usize]) -> Option<TransferModel> {
        let dlt = self.0.fit_inliers(data, inliers)?;
        let subset: Vec<Quadruplet> = inliers.iter().map(|&i| data[i]).collect();
        let refined = refine_transfer(&dlt, &self.0.p_left, &self.0.p_right, &subset).unwrap_or(dlt);
        (refined.h.0.determinant() > 0.0).then_some(refined)
    }

    fn residual(&self, model: &TransferModel, datum: &Quadruplet) -> f64 {
        self.0.residual(model, datum)
    }
}

/// Indices of the quadruplets consistent with a plane homography in both the left and the
/// right image pair (4-point RANSAC, `threshold_px`). If a RANSAC fails (too few
/// quadruplets), every quadruplet passes and the 3D stage decides.
fn screen_rotation(quads: &[Quadruplet], threshold_px: f64, seed: u64) -> (Vec<usize>, Option<PlanePair>) {
    let options = RansacOptions { threshold: threshold_px, seed, ..RansacOptions::default() };
    let left: Vec<(Point2<f64>, Point2<f64>)> = quads.iter().map(|q| (q.left0, q.left1)).collect();
    let right: Vec<(Point2<f64>, Point2<f64>)> = quads.iter().map(|q| (q.right0, q.right1)).collect();
    let keep = |data: &[(Point2<f64>, Point2<f64>)]| -> (Vec<bool>, Option<Matrix3<f64>>) {
        match ransac(&Homography2Estimator, data, &options) {
            Ok(rep) => {
                let mut mask = vec![false; data.len()];
                for i in rep.inliers {
                    mask[i] = true;
                }
                (mask, Some(rep.model.0))
            }
            Err(_) => (vec![true; data.len()], None),
        }
    };
    let ((l, gl), (r, gr)) = (keep(&left), keep(&right));
    let kept = (0..quads.len()).filter(|&i| l[i] && r[i]).collect();
    (kept, gl.zip(gr))
}

/// The plane homographies (left, right) of the rotation from `view0` to `view1` over the
/// image pairs of every track reconstructed in either view (`recon0`, `recon1`: a right
/// stereo match there makes the track's pixel in that view likely right, so a pair is
/// right about as often as one observation), by the 4-point RANSAC of
/// [`screen_rotation`] (threshold [`EstimationOptions::prefilter_px`]); `None` unless
/// both are found.
fn plane_rotations(
    view0: &View,
    view1: &View,
    (recon0, recon1): (&Reconstruction, &Reconstruction),
    options: &EstimationOptions,
) -> Option<PlanePair> {
    use std::collections::HashMap;
    let ransac_options =
        RansacOptions { threshold: options.prefilter_px, seed: options.seed, ..RansacOptions::default() };
    let image =
        |side: fn(&headalign_platform::StereoCapture) -> &Vec<headalign_platform::TrackObservation>| {
            let first: HashMap<u64, Point2<f64>> =
                side(&view0.capture).iter().map(|o| (o.track, o.pixel)).collect();
            let pairs: Vec<(Point2<f64>, Point2<f64>)> = side(&view1.capture)
                .iter()
                .filter(|o| recon0.contains_key(&o.track) || recon1.contains_key(&o.track))
                .filter_map(|o| first.get(&o.track).map(|p| (*p, o.pixel)))
                .collect();
            ransac(&Homography2Estimator, &pairs, &ransac_options).ok().map(|r| r.model.0)
        };
    image(|c| &c.left).zip(image(|c| &c.right))
}

/// `start` polished by Levenberg-Marquardt on the transfer error of `subset`; `None` if the
/// result is not a rigid conjugate (det <= 0).
pub(crate) fn polish(
    start: &TransferModel,
    quads: &[Quadruplet],
    subset: &[usize],
    p_l: &headalign_geometry::camera::ProjectiveCamera,
    p_r: &headalign_geometry::camera::ProjectiveCamera,
) -> Option<TransferModel> {
    let sub: Vec<Quadruplet> = subset.iter().map(|&i| quads[i]).collect();
    let m = refine_transfer(start, p_l, p_r, &sub).ok()?;
    (m.h.0.determinant() > 0.0).then_some(m)
}
