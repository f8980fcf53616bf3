//! Experiment: the localisation error of tracked image features against the simulator's
//! truth, and its structure across the views of a track (why the image-mode Gaussian
//! covariance was optimistic). `cargo run --release -p headalign --example track_errors -- SEED0 SEED1`
//!
//! Per seed: the image-mode verge/tilt views (verging, then the capture plan of the
//! default procedure, tracked by [`TrackingHead`] against the reference view). For every
//! track seen at least 4 times, the point is triangulated from all its observations
//! with the *true* cameras (N-view DLT), and each observation's residual is the
//! measured pixel minus the true projection: the localisation error the bundle
//! adjustment cannot explain even with a perfect calibration. Printed:
//! - the RMS residual per component, corrected for the 3 dof each point absorbs, against
//!   the estimator's noise estimate `sigma_px` on the same views;
//! - the correlation of a track's residuals between two views of the same camera (same
//!   component): 0 for i.i.d. noise (about -3/(2k) after the point fit), near 1 when the
//!   detector puts the same offset into every view;
//! - the reference-left ray cast onto the true surface and projected into the other
//!   views: the error of each observation against that surface point (left: the
//!   temporal tracking error; right: the stereo error);
//! - the estimate's `sigma_inflation` under the clustered covariance.
//!
//! `REFINE=off|temporal|stereo` in the environment: the front end without patch
//! refinement, with later observations refined only, or with stereo partners too
//! (`common::front_end_options`); unset: the default (`stereo`).
use std::collections::BTreeMap;

mod common;

use headalign::estimate::{EstimationOptions, estimate_rig};
use headalign_geometry::bundle::{BundleOptions, CovarianceModel};
use nalgebra::Vector2;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let s0: u64 = args.get(1).map_or(Ok(1), |s| s.parse())?;
    let s1: u64 = args.get(2).map_or(Ok(s0), |s| s.parse())?;
    for seed in s0..=s1 {
        let (head, views, true_enc) = common::tracked_rig_views(seed)?;
        let truth = head.truth().clone();
        let cams = common::true_view_cameras(&head, &true_enc);
        // track -> [(view, side, pixel)]
        let tracks = common::tracks_by_id(&views);
        let (mut ss, mut comps, mut dof) = (0.0, 0usize, 0usize);
        // Pairs of residuals (same track, same side, same component, different views).
        let (mut sxy, mut sxx, mut pairs) = (0.0, 0.0, 0usize);
        let mut per_track: Vec<f64> = Vec::new();
        // (view, side) -> (sum of residuals, count): an error common to a view's tracks.
        let mut view_mean: BTreeMap<(usize, usize), (Vector2<f64>, usize)> = BTreeMap::new();
        for obs in tracks.values().filter(|o| o.len() >= 4) {
            let Some(x) = common::triangulate_track(&cams, obs.iter().copied()) else { continue };
            let res: Vec<Option<Vector2<f64>>> =
                obs.iter().map(|(v, side, px)| cams[*v][*side].project(&x).map(|q| px - q)).collect();
            if res.iter().any(|r| r.is_none_or(|r| r.norm() > 3.0)) {
                continue; // a wrong track: not localisation noise
            }
            let res: Vec<Vector2<f64>> = res.into_iter().flatten().collect();
            for ((v, side, _), r) in obs.iter().zip(&res) {
                let e = view_mean.entry((*v, *side)).or_insert((Vector2::zeros(), 0usize));
                e.0 += r;
                e.1 += 1;
            }
            let t: f64 = res.iter().map(|r| r.norm_squared()).sum();
            ss += t;
            comps += 2 * res.len();
            dof += 2 * res.len() - 3;
            per_track.push((t / (2 * res.len() - 3) as f64).sqrt());
            for i in 0..obs.len() {
                for j in i + 1..obs.len() {
                    if obs[i].1 == obs[j].1 {
                        for (a, b) in res[i].iter().zip(res[j].iter()) {
                            sxy += a * b;
                            sxx += 0.5 * (a * a + b * b);
                            pairs += 1;
                        }
                    }
                }
            }
        }
        // Ray cast of the reference-left pixel onto the true surface.
        let (mut sl, mut nl, mut sr, mut nr) = (0.0, 0usize, 0.0, 0usize);
        // All ray-cast errors (no 3 px cut): how many exceed 1 px, and the RMS of those
        // under 3 px (both sides together).
        let (mut n_all, mut n_over1) = (0usize, 0usize);
        let (wl0, _) = head.scene_from_cameras(&true_enc[0]);
        for obs in tracks.values().filter(|o| o.len() >= 4) {
            let Some((_, _, p0)) = obs.iter().find(|(v, s, _)| *v == 0 && *s == 0) else { continue };
            let ray = truth.left.inverse_matrix() * nalgebra::Vector3::new(p0.x, p0.y, 1.0);
            let origin = nalgebra::Point3::from(wl0.translation.vector);
            let Some(xw) = head.room().cast(&origin, &(wl0.rotation * ray)) else { continue };
            for (v, side, px) in obs {
                if *v == 0 && *side == 0 {
                    continue;
                }
                let (ql, qr) = head.exact_pixels(&true_enc[*v], &xw);
                let q = if *side == 0 { ql } else { qr };
                let Some(q) = q else { continue };
                let e = (px - q).norm_squared();
                n_all += 1;
                n_over1 += usize::from(e > 1.0);
                if e > 9.0 {
                    continue;
                }
                if *side == 0 {
                    sl += e;
                    nl += 1;
                } else {
                    sr += e;
                    nr += 1;
                }
            }
        }
        let common: Vec<String> = view_mean
            .iter()
            .map(|((v, side), (sum, n))| {
                let m = sum / (*n).max(1) as f64;
                format!("v{v}{}({:+.3},{:+.3})", if *side == 0 { "L" } else { "R" }, m.x, m.y)
            })
            .collect();
        println!("seed {seed}: mean true-camera residual per view and camera, px: {}", common.join(" "));
        println!(
            "seed {seed}: ray-cast observations {n_all}, over 1 px {:.1} %, RMS/component under 3 px {:.3} px",
            100.0 * n_over1 as f64 / n_all.max(1) as f64,
            ((sl + sr) / (2 * (nl + nr).max(1)) as f64).sqrt()
        );
        let d = EstimationOptions { seed, ..EstimationOptions::default() };
        let gauss = estimate_rig(&views, &d)?;
        let clustered = EstimationOptions {
            bundle: BundleOptions { covariance_model: CovarianceModel::PointClustered, ..d.bundle.clone() },
            ..d
        };
        let cl = estimate_rig(&views, &clustered)?;
        per_track.sort_by(f64::total_cmp);
        let q = |f: f64| per_track.get((f * per_track.len() as f64) as usize).copied().unwrap_or(f64::NAN);
        let cmp = |n: &str| {
            let (a, b) = (gauss.bundle.covariance.sigma(n), cl.bundle.covariance.sigma(n));
            format!("{n} {:.3}/{:.3}", a.unwrap_or(f64::NAN), b.unwrap_or(f64::NAN))
        };
        println!(
            "seed {seed}: tracks {} (>= 4 obs), true-camera residual {:.3} px/component (dof-corrected; raw {:.3}), per-track sigma 10/50/90 % {:.2}/{:.2}/{:.2}; same-camera cross-view correlation {:+.2} ({} pairs); ray-cast error RMS/component left {:.3} ({}), right {:.3} ({}); estimator sigma_px {:.3}, clustered inflation {:.2}; sigmas gaussian/clustered: {}, {}, {}, {}",
            per_track.len(),
            (ss / dof.max(1) as f64).sqrt(),
            (ss / comps.max(1) as f64).sqrt(),
            q(0.1),
            q(0.5),
            q(0.9),
            sxy / sxx.max(1e-300),
            pairs,
            (sl / (2 * nl.max(1)) as f64).sqrt(),
            nl,
            (sr / (2 * nr.max(1)) as f64).sqrt(),
            nr,
            gauss.bundle.report.sigma_px,
            cl.bundle.report.sigma_inflation,
            cmp("left.fx"),
            cmp("left.cx"),
            cmp("right.fy"),
            cmp("right.cy"),
        );
    }
    Ok(())
}
