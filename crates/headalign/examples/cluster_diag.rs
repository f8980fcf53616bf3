//! Experiment: why the image-mode (track-clustered) sigmas are optimistic.
//! `cargo run --release -p headalign --example cluster_diag -- SEED0 SEED1 [DRAWS]`
//!
//! Per seed: the image-mode verge/tilt views (as `track_errors.rs`), estimated with the
//! track-clustered covariance (image mode's). The simulator's truth is used only here:
//! - every track's point is triangulated from all its observations with the *true*
//!   cameras; an observation's localisation error `e` is its pixel minus the true
//!   projection of that point;
//! - **cross-track correlation**: per image, pairs of tracks binned by their distance in
//!   the image, `sum e_i . e_j / sum (|e_i|^2 + |e_j|^2) / 2` (0 for independent errors);
//! - **coarser clusters**: z-scores (estimate - truth) / sigma of the 8 intrinsics under
//!   the covariance clustered per track, per image region of the track's first
//!   observation (100 and 200 px cells), per surface of the room (true ray cast);
//! - **substitution**: the final adjustment re-run from the estimate on synthetic pixels
//!   `true projection + e'`, with `e'` the measured errors themselves (checks the
//!   apparatus), i.i.d. Gaussian of the global RMS, Gaussian with each track's own RMS,
//!   and the measured error sets shuffled between tracks seen in the same views (keeps
//!   each track's error structure, breaks any correlation between neighbours), also
//!   only within an image region, surface or depth quintile; the measured errors without
//!   the tracks at true depth steps (ray casts 4 px around differ by over 10 % in
//!   distance), without those [`near_depth_step`] flags at run time, and without as many
//!   random tracks (control);
//! - per image, an affine field of the errors over the pixel position (F statistic) and
//!   the mean error per depth quintile, 3x3 region and track length (chi-square/dof).
//!
//! Printed at the end: RMS z per variant over seeds and intrinsics.
use std::collections::BTreeMap;

mod common;

use headalign::estimate::{DepthStepGate, EstimationOptions, estimate_rig, near_depth_step};
use headalign_geometry::bundle::{
    BundleObservation, BundleOptions, BundleResult, CovarianceModel, RigState, RobustLoss, Side,
    bundle_adjust, clustered_covariance,
};
use nalgebra::{DMatrix, Point2, Point3, Vector2, Vector4};
use rand::seq::SliceRandom;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// A pixel and its localisation error.
type PixelError = (Point2<f64>, Vector2<f64>);
/// Tracks grouped by (category, the images they are seen in).
type Groups = BTreeMap<(usize, Vec<(usize, usize)>), Vec<usize>>;

const NAMES: [&str; 8] =
    ["left.fx", "left.fy", "left.cx", "left.cy", "right.fx", "right.fy", "right.cx", "right.cy"];

fn value(state: &RigState, name: &str) -> f64 {
    let (k, p) = name.split_once('.').unwrap_or(("left", "fx"));
    let k = if k == "left" { &state.left } else { &state.right };
    match p {
        "fx" => k.fx,
        "fy" => k.fy,
        "cx" => k.cx,
        _ => k.cy,
    }
}

fn zs(state: &RigState, truth: &RigState, sigma: &dyn Fn(&str) -> Option<f64>) -> Vec<f64> {
    NAMES.iter().map(|n| (value(state, n) - value(truth, n)) / sigma(n).unwrap_or(f64::NAN)).collect()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let s0: u64 = args.get(1).map_or(Ok(1), |s| s.parse())?;
    let s1: u64 = args.get(2).map_or(Ok(s0), |s| s.parse())?;
    let draws: usize = args.get(3).map_or(Ok(3), |s| s.parse())?;
    let mut all: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let mut corr_all: BTreeMap<usize, (f64, f64, usize)> = BTreeMap::new();
    let mut chi_all: BTreeMap<String, (f64, usize)> = BTreeMap::new();
    for seed in s0..=s1 {
        let (head, views, true_enc) = common::tracked_rig_views(seed)?;
        let truth = head.truth().clone();
        let cams = common::true_view_cameras(&head, &true_enc);
        let d = EstimationOptions::default();
        let options = EstimationOptions {
            seed,
            bundle: BundleOptions { covariance_model: CovarianceModel::PointClustered, ..d.bundle.clone() },
            ..d
        };
        let calib = estimate_rig(&views, &options)?;
        let state = &calib.bundle.state;
        let mut truth_state = state.clone();
        truth_state.left = truth.left;
        truth_state.right = truth.right;
        let obs = &calib.observations;
        let np = state.points.len();
        // True-camera triangulation of each bundle point from its used observations.
        let mut by_point: Vec<Vec<&BundleObservation>> = vec![Vec::new(); np];
        for o in obs {
            by_point[o.point].push(o);
        }
        let side_of = |s: Side| usize::from(s == Side::Right);
        let mut true_point: Vec<Option<Vector4<f64>>> = vec![None; np];
        for (p, list) in by_point.iter().enumerate() {
            if list.len() < 2 {
                continue;
            }
            true_point[p] =
                common::triangulate_track(&cams, list.iter().map(|o| (o.view, side_of(o.side), o.pixel)));
        }
        let proj = |o: &BundleObservation| -> Option<Point2<f64>> {
            true_point[o.point].and_then(|x| cams[o.view][side_of(o.side)].project(&x))
        };
        let errors: Vec<Option<Vector2<f64>>> = obs.iter().map(|o| proj(o).map(|q| o.pixel - q)).collect();
        // Cross-track correlation per image, binned by distance.
        let bins = [8.0, 20.0, 50.0, 120.0, 300.0, 2000.0];
        let mut per_image: BTreeMap<(usize, usize), Vec<PixelError>> = BTreeMap::new();
        for (o, e) in obs.iter().zip(&errors) {
            if let Some(e) = e
                && by_point[o.point].len() >= 3
            {
                per_image.entry((o.view, side_of(o.side))).or_default().push((o.pixel, *e));
            }
        }
        let mut corr: BTreeMap<usize, (f64, f64, usize)> = BTreeMap::new();
        for list in per_image.values() {
            for i in 0..list.len() {
                for j in i + 1..list.len() {
                    let dist = (list[i].0 - list[j].0).norm();
                    let Some(b) = bins.iter().position(|&b| dist < b) else { continue };
                    let c = corr.entry(b).or_insert((0.0, 0.0, 0));
                    c.0 += list[i].1.dot(&list[j].1);
                    c.1 += 0.5 * (list[i].1.norm_squared() + list[j].1.norm_squared());
                    c.2 += 1;
                }
            }
        }
        let corr_text: Vec<String> = corr
            .iter()
            .map(|(b, (xy, xx, n))| {
                let a = corr_all.entry(*b).or_insert((0.0, 0.0, 0));
                a.0 += xy;
                a.1 += xx;
                a.2 += n;
                format!("<{}px {:+.3} ({n})", bins[*b], xy / xx)
            })
            .collect();
        println!("seed {seed}: cross-track error correlation by image distance: {}", corr_text.join(", "));

        // Cluster labels.
        let first_pixel: Vec<Option<(usize, Point2<f64>)>> = by_point
            .iter()
            .map(|l| {
                l.iter()
                    .find(|o| o.view == 0 && o.side == Side::Left)
                    .or(l.first())
                    .map(|o| (o.view * 2 + side_of(o.side), o.pixel))
            })
            .collect();
        let region = |cell: f64| -> Vec<usize> {
            (0..np)
                .map(|p| match first_pixel[p] {
                    Some((img, px)) => {
                        1_000_000
                            + img * 10_000
                            + (px.y / cell).floor() as usize * 100
                            + (px.x / cell).floor() as usize
                    }
                    None => p,
                })
                .collect()
        };
        let quads = head.room().quads();
        let surface: Vec<usize> = (0..np)
            .map(|p| {
                let Some(x) = true_point[p] else { return p };
                if x[3].abs() < 1e-12 {
                    return p;
                }
                let xw = Point3::new(x[0] / x[3], x[1] / x[3], x[2] / x[3]);
                let best = quads
                    .iter()
                    .enumerate()
                    .map(|(i, q)| (i, (xw - q.corner).dot(&q.normal()).abs()))
                    .min_by(|a, b| a.1.total_cmp(&b.1));
                match best {
                    Some((i, dist)) if dist < 0.02 => 2_000_000 + i,
                    _ => p,
                }
            })
            .collect();
        // Tracks at a depth discontinuity (true ray casts 4 px around the first observation
        // differ in distance by more than 10 %): their "corner" may be where a near edge
        // crosses the background, which is no fixed point of the scene.
        let boundary: Vec<bool> = (0..np)
            .map(|p| {
                let Some(o) = by_point[p].first() else { return false };
                let (wl, wr) = head.scene_from_cameras(&true_enc[o.view]);
                let (pose, k) = if o.side == Side::Left { (wl, &truth.left) } else { (wr, &truth.right) };
                let origin = Point3::from(pose.translation.vector);
                let dist = |dx: f64, dy: f64| {
                    let ray =
                        k.inverse_matrix() * nalgebra::Vector3::new(o.pixel.x + dx, o.pixel.y + dy, 1.0);
                    head.room().cast(&origin, &(pose.rotation * ray)).map(|h| (h - origin).norm())
                };
                let Some(d0) = dist(0.0, 0.0) else { return false };
                [(4.0, 0.0), (-4.0, 0.0), (0.0, 4.0), (0.0, -4.0)]
                    .iter()
                    .any(|(dx, dy)| dist(*dx, *dy).is_none_or(|d| (d - d0).abs() > 0.1 * d0))
            })
            .collect();
        {
            let (mut sb, mut nb, mut so, mut no) = (0.0, 0usize, 0.0, 0usize);
            for (o, e) in obs.iter().zip(&errors) {
                if let Some(e) = e {
                    if boundary[o.point] {
                        sb += e.norm_squared();
                        nb += 1;
                    } else {
                        so += e.norm_squared();
                        no += 1;
                    }
                }
            }
            let nbt = (0..np).filter(|&p| boundary[p] && !by_point[p].is_empty()).count();
            let nt = (0..np).filter(|&p| !by_point[p].is_empty()).count();
            println!(
                "seed {seed}: boundary tracks {nbt} of {nt}; error RMS/component boundary {:.3} px ({nb} obs), others {:.3} px ({no} obs)",
                (sb / (2 * nb.max(1)) as f64).sqrt(),
                (so / (2 * no.max(1)) as f64).sqrt()
            );
        }
        let sigma_px = calib.bundle.report.sigma_px;
        let ml = BundleOptions {
            max_iterations: 100,
            robust: RobustLoss::None,
            noise_sigma_px: Some(sigma_px),
            ..options.bundle.clone()
        };
        let mut line = Vec::new();
        let mut record = |name: &str, z: Vec<f64>, line: &mut Vec<String>| {
            let rms = (z.iter().map(|v| v * v).sum::<f64>() / z.len() as f64).sqrt();
            line.push(format!("{name} {rms:.2}"));
            all.entry(name.to_string()).or_default().extend(z);
        };
        let gauss = bundle_adjust(
            state,
            obs,
            &BundleOptions { max_iterations: 0, covariance_model: CovarianceModel::Gaussian, ..ml.clone() },
        )?;
        record("gaussian", zs(state, &truth_state, &|n| gauss.covariance.sigma(n)), &mut line);
        record("track", zs(state, &truth_state, &|n| calib.bundle.covariance.sigma(n)), &mut line);
        for (name, labels) in
            [("region100", region(100.0)), ("region200", region(200.0)), ("surface", surface.clone())]
        {
            let c = clustered_covariance(state, obs, &ml, sigma_px, &labels)?;
            let clusters = labels.iter().collect::<std::collections::HashSet<_>>().len();
            record(name, zs(state, &truth_state, &|n| c.sigma(n)), &mut line);
            line.push(format!("({clusters} clusters)"));
        }
        println!("seed {seed}: z RMS over the intrinsics: {}", line.join(" "));

        // Substitution.
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let all_e: Vec<Vector2<f64>> = errors.iter().flatten().copied().collect();
        let global = (all_e.iter().map(|e| e.norm_squared()).sum::<f64>() / (2 * all_e.len()) as f64).sqrt();
        let mut track_rms = vec![global; np];
        for (p, list) in by_point.iter().enumerate() {
            let es: Vec<Vector2<f64>> =
                obs.iter().zip(&errors).filter(|(o, _)| o.point == p).filter_map(|(_, e)| *e).collect();
            if es.len() >= 2 && list.len() >= 2 {
                let dof = (2 * es.len()).saturating_sub(3).max(1) as f64;
                track_rms[p] = (es.iter().map(|e| e.norm_squared()).sum::<f64>() / dof).sqrt();
            }
        }
        // Tracks grouped by their (view, side) pattern, for the shuffle.
        // Depth bins (quintiles of the estimated points' distance).
        let mut depths: Vec<f64> = (0..np).map(|p| state.points[p].coords.norm()).collect();
        depths.sort_by(f64::total_cmp);
        let depth_bin = |p: usize| {
            let d = state.points[p].coords.norm();
            (1..5).filter(|i| d > depths[i * np / 5]).count()
        };
        let reg100 = region(100.0);
        let patterns_by = |cat: &dyn Fn(usize) -> usize| {
            let mut patterns: Groups = BTreeMap::new();
            for (p, list) in by_point.iter().enumerate() {
                if list.len() >= 2 && true_point[p].is_some() {
                    let mut key: Vec<(usize, usize)> =
                        list.iter().map(|o| (o.view, side_of(o.side))).collect();
                    key.sort_unstable();
                    patterns.entry((cat(p), key)).or_default().push(p);
                }
            }
            patterns
        };
        let shuffles: Vec<(&str, Groups)> = vec![
            ("shuffled", patterns_by(&|_| 0)),
            ("shuf-in-region", patterns_by(&|p| reg100[p])),
            ("shuf-in-surface", patterns_by(&|p| surface[p])),
            ("shuf-in-depth", patterns_by(&|p| depth_bin(p))),
        ];
        // Per image: the share of the errors an affine field of the pixel position explains,
        // as an F statistic (1 for independent errors).
        let mut fstats = Vec::new();
        for ((v, side), list) in &per_image {
            let n = list.len();
            if n < 50 {
                continue;
            }
            let mut a = DMatrix::zeros(n, 3);
            let mut bx = nalgebra::DVector::zeros(n);
            let mut by = nalgebra::DVector::zeros(n);
            for (i, (px, e)) in list.iter().enumerate() {
                a[(i, 0)] = 1.0;
                a[(i, 1)] = (px.x - 400.0) / 400.0;
                a[(i, 2)] = (px.y - 300.0) / 400.0;
                bx[i] = e.x;
                by[i] = e.y;
            }
            let svd = a.clone().svd(true, true);
            let (mut expl, mut total) = (0.0, 0.0);
            for b in [&bx, &by] {
                if let Ok(x) = svd.solve(b, 1e-12) {
                    let fit = &a * x;
                    expl += fit.norm_squared();
                    total += b.norm_squared();
                }
            }
            let f = (expl / 6.0) / ((total - expl) / (2 * n - 6) as f64);
            fstats.push(format!("v{v}{}:{f:.1}", if *side == 0 { "L" } else { "R" }));
        }
        println!("seed {seed}: affine-field F per image (1 if independent): {}", fstats.join(" "));
        // Mean error per (image, category) cell against its standard error: chi^2 per
        // degree of freedom (1 for errors independent of the category).
        for (cname, cat) in [
            ("depth quintile", &depth_bin as &dyn Fn(usize) -> usize),
            ("3x3 region", &|p: usize| {
                first_pixel[p].map_or(0, |(_, px)| {
                    (px.x / 267.0).floor() as usize + 3 * (px.y / 200.0).floor() as usize
                })
            }),
            ("track length", &|p: usize| by_point[p].len().min(10)),
        ] {
            let mut cells: BTreeMap<(usize, usize, usize), Vec<Vector2<f64>>> = BTreeMap::new();
            for (o, e) in obs.iter().zip(&errors) {
                if let Some(e) = e {
                    cells.entry((o.view, side_of(o.side), cat(o.point))).or_default().push(*e);
                }
            }
            let (mut chi, mut dof) = (0.0, 0usize);
            for list in cells.values().filter(|l| l.len() >= 10) {
                let n = list.len() as f64;
                let m = list.iter().sum::<Vector2<f64>>() / n;
                let var =
                    list.iter().map(|e| (e - m).component_mul(&(e - m))).sum::<Vector2<f64>>() / (n - 1.0);
                chi += m.x * m.x / (var.x / n) + m.y * m.y / (var.y / n);
                dof += 2;
            }
            println!(
                "seed {seed}: mean error per image and {cname}: chi2/dof {:.2} ({dof} dof)",
                chi / dof.max(1) as f64
            );
            *chi_all.entry(cname.to_string()).or_insert((0.0, 0)) =
                (chi_all.get(cname).map_or(0.0, |c| c.0) + chi, chi_all.get(cname).map_or(0, |c| c.1) + dof);
        }
        let mut run = |name: &str, pixel: &dyn Fn(usize, &BundleObservation) -> Option<Point2<f64>>| {
            let synth: Vec<BundleObservation> = obs
                .iter()
                .enumerate()
                .filter_map(|(i, o)| pixel(i, o).map(|px| BundleObservation { pixel: px, ..*o }))
                .collect();
            let r: Result<BundleResult, _> = bundle_adjust(state, &synth, &ml);
            match r {
                Ok(r) => {
                    let z = zs(&r.state, &truth_state, &|n| r.covariance.sigma(n));
                    let rms = (z.iter().map(|v| v * v).sum::<f64>() / z.len() as f64).sqrt();
                    all.entry(format!("subst-{name}")).or_default().extend(z);
                    format!("{name} {rms:.2}")
                }
                Err(e) => format!("{name} failed ({e})"),
            }
        };
        let measured = |i: usize, o: &BundleObservation| {
            errors[i].and(proj(o)).map(|q| q + errors[i].unwrap_or_default())
        };
        let mut sub = vec![run("measured", &measured)];
        sub.push(run("no-boundary", &|i, o| if boundary[o.point] { None } else { measured(i, o) }));
        // Run-time stand-in: a track whose image neighbours (first observations in the same
        // image within RADIUS px) lie at a depth differing by more than RATIO.
        for (radius, ratio) in [(25.0, 1.2), (40.0, 1.15)] {
            let flagged = near_depth_step(state, obs, &DepthStepGate { radius_px: radius, ratio });
            let nf = (0..np).filter(|&p| flagged[p] && !by_point[p].is_empty()).count();
            let both = (0..np).filter(|&p| flagged[p] && boundary[p] && !by_point[p].is_empty()).count();
            let name = format!("no-flagged{radius}");
            let r = run(&name, &|i, o| if flagged[o.point] { None } else { measured(i, o) });
            sub.push(format!("{r} [{nf} flagged, {both} of them at a true boundary]"));
        }
        let mut others: Vec<usize> = (0..np).filter(|&p| !boundary[p] && !by_point[p].is_empty()).collect();
        others.shuffle(&mut rng);
        let nbt = (0..np).filter(|&p| boundary[p] && !by_point[p].is_empty()).count();
        let mut dropped = vec![false; np];
        for &p in others.iter().take(nbt) {
            dropped[p] = true;
        }
        sub.push(run("drop-random", &|i, o| if dropped[o.point] { None } else { measured(i, o) }));
        for _ in 0..draws {
            let noise: Vec<Vector2<f64>> = (0..obs.len())
                .map(|_| {
                    Vector2::new(rng.sample::<f64, _>(StandardNormal), rng.sample::<f64, _>(StandardNormal))
                })
                .collect();
            sub.push(run("iid", &|i, o| errors[i].and(proj(o)).map(|q| q + noise[i] * global)));
            sub.push(run("per-track", &|i, o| {
                errors[i].and(proj(o)).map(|q| q + noise[i] * track_rms[o.point])
            }));
            let lookup: BTreeMap<(usize, usize, usize), Vector2<f64>> = obs
                .iter()
                .zip(&errors)
                .filter_map(|(o, e)| e.map(|e| ((o.point, o.view, side_of(o.side)), e)))
                .collect();
            for (name, patterns) in &shuffles {
                // Shuffle whole tracks' error sets within each group.
                let mut source = vec![usize::MAX; np];
                for group in patterns.values() {
                    let mut g = group.clone();
                    g.shuffle(&mut rng);
                    for (a, b) in group.iter().zip(&g) {
                        source[*a] = *b;
                    }
                }
                sub.push(run(name, &|_, o| {
                    let src = *source.get(o.point)?;
                    let e = lookup.get(&(src, o.view, side_of(o.side)))?;
                    proj(o).map(|q| q + e)
                }));
            }
        }
        println!("seed {seed}: substitution z RMS (global e RMS {global:.3} px): {}", sub.join(" "));
    }
    println!("== over seeds {s0}-{s1}: RMS z of the 8 intrinsics");
    for (name, z) in &all {
        let z: Vec<f64> = z.iter().copied().filter(|v| v.is_finite()).collect();
        let rms = (z.iter().map(|v| v * v).sum::<f64>() / z.len().max(1) as f64).sqrt();
        let cov = z.iter().filter(|v| v.abs() <= 1.96).count() as f64 / z.len().max(1) as f64;
        let mean = z.iter().sum::<f64>() / z.len().max(1) as f64;
        println!("  {name:22} RMS {rms:.2} mean {mean:+.2} coverage {:.0} % (n {})", 100.0 * cov, z.len());
    }
    let c: Vec<String> =
        corr_all.iter().map(|(b, (xy, xx, n))| format!("bin{b} {:+.3} ({n})", xy / xx)).collect();
    for (name, (chi, dof)) in &chi_all {
        println!("  mean error per image and {name}: chi2/dof {:.2} ({dof} dof)", chi / (*dof).max(1) as f64);
    }
    println!("  cross-track correlation by distance bin (8/20/50/120/300/2000 px): {}", c.join(", "));
    Ok(())
}
