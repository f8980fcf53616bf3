//! The stereo matches a check works on ([`super`] module docs, "Method" step 1): each
//! pair's own left-right matches (the front end of `calibrate`,
//! [`crate::calibrate::views::stereo_only`]: corners, descriptor matches, `F` by RANSAC,
//! guided matching, the right corner aligned against its left partner's patch), the given
//! lenses removed ([`crate::rig::undistort_views`]), and the vertical disparity
//! after the given rectification ([`vertical_disparity`]).
//!
//! Units: pixels (undistorted pinhole pixels of the given intrinsics). Pitfalls: a match
//! whose undistortion fails (outside the lens model's valid range) is dropped.

use std::collections::HashMap;

use headalign_geometry::rectify::Rectification;
use nalgebra::{Matrix3, Point2, Vector3};

use super::refit::Match;
use crate::observations::View;

/// One pair's undistorted matches.
#[derive(Debug, Clone)]
pub struct PairMatches {
    /// The pair's name.
    pub name: String,
    /// `(left, right)` undistorted pixels.
    pub matches: Vec<Match>,
}

/// Each view's left-right matches (observations of the same track in both images).
pub fn pair_matches(views: &[View]) -> Vec<PairMatches> {
    views
        .iter()
        .map(|v| {
            let right: HashMap<u64, Point2<f64>> =
                v.capture.right.iter().map(|o| (o.track, o.pixel)).collect();
            let matches =
                v.capture.left.iter().filter_map(|o| right.get(&o.track).map(|r| (o.pixel, *r))).collect();
            PairMatches { name: v.name.clone(), matches }
        })
        .collect()
}

/// The rectified pixel of `pixel` (undistorted, in a camera with `k_inv`) under the
/// rectification rotation `rect` and the rectified camera matrix `k_rect`.
fn rectified(
    k_rect: &Matrix3<f64>,
    rect: &Matrix3<f64>,
    k_inv: &Matrix3<f64>,
    p: &Point2<f64>,
) -> Option<Point2<f64>> {
    let x = k_rect * rect * k_inv * Vector3::new(p.x, p.y, 1.0);
    (x.z.abs() > 0.0).then(|| Point2::new(x.x / x.z, x.y / x.z))
}

/// `|y_left - y_right|` of each match after the rectification `rect` (pixels), the cameras'
/// inverse intrinsics `k_inv = [K_L^-1, K_R^-1]`.
pub fn vertical_disparity(
    rect: &Rectification,
    k_inv: [&Matrix3<f64>; 2],
    matches: &[Match],
    selected: &[usize],
) -> Vec<f64> {
    let kl = rect.p_left.fixed_view::<3, 3>(0, 0).into_owned();
    let kr = rect.p_right.fixed_view::<3, 3>(0, 0).into_owned();
    selected
        .iter()
        .filter_map(|&i| {
            let (l, r) = &matches[i];
            let a = rectified(&kl, &rect.rect_from_left, k_inv[0], l)?;
            let b = rectified(&kr, &rect.rect_from_right, k_inv[1], r)?;
            Some((a.y - b.y).abs())
        })
        .collect()
}
