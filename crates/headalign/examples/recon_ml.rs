//! Diagnostic: is the reconstruction error of the 50-point bar (1.5 px, 3 deg rotations)
//! the maximum-likelihood estimate's own, or an estimator weakness (a local minimum, a
//! bad inlier set)? `cargo run --release -p headalign --example recon_ml -- [FIRST LAST [v]]`
//!
//! Per seed: the verge/tilt procedure as `headalign experiment points` runs it (RANSAC and
//! prefilter thresholds x 1.5), the reconstruction error as the experiment scores it
//! (points observed at least 3 times, best least-squares similarity onto the truth, error
//! in percent of each point's true distance from the left camera), the rig's errors (the
//! right camera's rotation and the baseline direction, degrees), and then the same bundle
//! adjustment on the same inliers started from the truth (the noise-free run's motions,
//! true intrinsics and points, in the estimator's gauge): if it ends at the estimate's cost
//! and reconstruction, the estimate is the likelihood's minimum and its error is not the
//! estimator's. `v` prints every point (true distance, observations, error).
use headalign::estimate::EstimationOptions;
use headalign::procedure::{VergeTiltOptions, VergeTiltRun};
use headalign_geometry::bundle::{RobustLoss, bundle_adjust};
use headalign_geometry::registration::similarity_fit;
use headalign_sim::{Scenario, SimulatedHead};
use nalgebra::Point3;

/// RMS over points of the error after the best similarity, percent of the true distance.
fn recon_rms(
    est: &[Point3<f64>],
    truth: &[Point3<f64>],
) -> Result<(f64, Vec<f64>), Box<dyn std::error::Error>> {
    let sim = similarity_fit(est, truth, true)?;
    let rel: Vec<f64> =
        est.iter().zip(truth).map(|(a, b)| (sim.transform(a) - b).norm() / b.coords.norm()).collect();
    Ok(((rel.iter().map(|v| v * v).sum::<f64>() / rel.len() as f64).sqrt() * 100.0, rel))
}

/// The same error after the similarity that minimises it (weights `1 / |truth|^2`,
/// weighted Umeyama): how much of the error is the least-squares similarity's choice.
fn recon_rms_weighted(est: &[Point3<f64>], truth: &[Point3<f64>]) -> f64 {
    let w: Vec<f64> = truth.iter().map(|p| 1.0 / p.coords.norm_squared()).collect();
    let sw: f64 = w.iter().sum();
    let mx = est.iter().zip(&w).map(|(p, wi)| p.coords * *wi).sum::<nalgebra::Vector3<f64>>() / sw;
    let my = truth.iter().zip(&w).map(|(p, wi)| p.coords * *wi).sum::<nalgebra::Vector3<f64>>() / sw;
    let mut cov = nalgebra::Matrix3::zeros();
    let mut var_x = 0.0;
    for ((x, y), wi) in est.iter().zip(truth).zip(&w) {
        let (dx, dy) = (x.coords - mx, y.coords - my);
        cov += dy * dx.transpose() * *wi;
        var_x += wi * dx.norm_squared();
    }
    let svd = cov.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else { return f64::NAN };
    let mut d = nalgebra::Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = u * d * vt;
    let scale = (nalgebra::Matrix3::from_diagonal(&svd.singular_values) * d).trace() / var_x;
    let t = my - r * mx * scale;
    let sum: f64 = est
        .iter()
        .zip(truth)
        .map(|(x, y)| ((r * x.coords * scale + t) - y.coords).norm_squared() / y.coords.norm_squared())
        .sum();
    (sum / est.len() as f64).sqrt() * 100.0
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let first: u64 = args.get(1).map_or(Ok(1), |s| s.parse())?;
    let last: u64 = args.get(2).map_or(Ok(30), |s| s.parse())?;
    let verbose = args.get(3).is_some();
    let (mut same, mut total) = (0, 0);
    let (mut sum_sq, mut sum_sq_w) = (0.0, 0.0);
    for seed in first..=last {
        let scenario = Scenario { seed, noise_px: 1.5, points: 50, ..Scenario::default() };
        let estimation = EstimationOptions::scaled_for_noise(1.5, seed);
        let opts = VergeTiltOptions {
            rotation_deg: 3.0,
            verge_rotation_deg: 3.0,
            estimation,
            ..VergeTiltOptions::default()
        };
        let mut head = SimulatedHead::new(scenario.clone())?;
        let out = VergeTiltRun::default().run(&mut head, &opts)?;
        let mut clean_head = SimulatedHead::new(Scenario { noise_px: 0.0, ..scenario })?;
        let clean = VergeTiltRun::default().run(&mut clean_head, &opts)?;
        let cal = &out.calibration;
        let by_id: std::collections::HashMap<u64, Point3<f64>> =
            head.scene_points().iter().copied().collect();
        let (world_from_left, world_from_right) = head.scene_from_cameras(&cal.reference_encoders);
        let left_from_world = world_from_left.inverse();
        let kept: Vec<usize> =
            (0..cal.point_tracks.len()).filter(|&i| cal.point_observations[i] >= 3).collect();
        let truth: Vec<Point3<f64>> =
            kept.iter().map(|&i| left_from_world * by_id[&cal.point_tracks[i]]).collect();
        let est: Vec<Point3<f64>> = kept.iter().map(|&i| cal.bundle.state.points[i]).collect();
        let (rms, rel) = recon_rms(&est, &truth)?;
        let weighted = recon_rms_weighted(&est, &truth);
        sum_sq += rms * rms;
        sum_sq_w += weighted * weighted;
        let true_rfl = world_from_right.inverse() * world_from_left;
        let est_rfl = cal.bundle.state.right_from_left;
        let rot_err = (true_rfl.rotation.inverse() * est_rfl.rotation).angle().to_degrees();
        let (tt, te) = (true_rfl.translation.vector.normalize(), est_rfl.translation.vector.normalize());
        let baseline_err = tt.dot(&te).clamp(-1.0, 1.0).acos().to_degrees();
        // The same least squares on the same inliers, from the truth.
        let mut start = clean.calibration.bundle.state.clone();
        let baseline = true_rfl.translation.vector.norm();
        start.points = cal
            .point_tracks
            .iter()
            .map(|t| Point3::from((left_from_world * by_id[t]).coords / baseline))
            .collect();
        let mut o = EstimationOptions::default().bundle;
        o.robust = RobustLoss::None;
        o.noise_sigma_px = Some(cal.bundle.report.sigma_px);
        o.max_iterations = 50;
        let from_truth = bundle_adjust(&start, &cal.observations, &o)?;
        let est2: Vec<Point3<f64>> = kept.iter().map(|&i| from_truth.state.points[i]).collect();
        let (rms2, _) = recon_rms(&est2, &truth)?;
        let (c1, c2) = (cal.bundle.report.final_rms_px, from_truth.report.final_rms_px);
        total += 1;
        if (c2 / c1 - 1.0).abs() < 1e-4 {
            same += 1;
        }
        let dist: Vec<f64> = truth.iter().map(|p| p.coords.norm()).collect();
        println!(
            "seed {seed:2}: {:2} points {:.1}-{:.1} m, recon {rms:6.2} % (weighted similarity {weighted:6.2} %), right rotation {rot_err:.2} deg, baseline direction {baseline_err:5.1} deg | from the truth: rms {c2:.5} px (estimate {c1:.5}), recon {rms2:6.2} %",
            kept.len(),
            dist.iter().copied().fold(f64::INFINITY, f64::min),
            dist.iter().copied().fold(0.0, f64::max),
        );
        if verbose {
            let mut idx: Vec<usize> = (0..rel.len()).collect();
            idx.sort_by(|a, b| rel[*b].total_cmp(&rel[*a]));
            for i in idx {
                println!(
                    "    {:5.2} m, {:2} observations, {:6.2} %, estimate at {:.1} m",
                    dist[i],
                    cal.point_observations[kept[i]],
                    100.0 * rel[i],
                    est[i].coords.norm() * baseline
                );
            }
        }
    }
    println!("{same}/{total} seeds: the bundle adjustment from the truth ends at the estimate's cost (1e-4)");
    let n = total.max(1) as f64;
    println!(
        "RMS over seeds: {:.2} % (least-squares similarity), {:.2} % (similarity minimising the relative error)",
        (sum_sq / n).sqrt(),
        (sum_sq_w / n).sqrt()
    );
    Ok(())
}
