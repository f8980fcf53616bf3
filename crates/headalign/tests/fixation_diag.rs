//! Diagnostics (ignored): where the error of fixating an unseen target comes from.
use headalign::imaging::{Camera, FixationOptions, fixate};
use headalign_platform::StereoHead;
use headalign_sim::{Scenario, SimulatedHead};
use nalgebra::{Isometry3, Point3};

fn pixel_of(h: &SimulatedHead, wl: &Isometry3<f64>, p: &Point3<f64>) -> Option<[f64; 2]> {
    let k = h.truth().left;
    let q = wl.inverse() * p;
    (q.z > 0.0).then(|| [k.fx * q.x / q.z + k.skew * q.y / q.z + k.cx, k.fy * q.y / q.z + k.cy])
}

/// Distance along the ray from `o` in direction `d` to the first visible surface.
fn first_hit(h: &SimulatedHead, o: &Point3<f64>, d: &nalgebra::Vector3<f64>) -> f64 {
    let mut best = f64::INFINITY;
    for q in h.room().quads() {
        let n = q.normal();
        let denom = n.dot(d);
        if denom.abs() < 1e-12 {
            continue;
        }
        let t = n.dot(&(q.corner - o)) / denom;
        if t <= 1e-6 || t >= best {
            continue;
        }
        let x = o + d * t - q.corner;
        let (a, b) = (x.dot(&q.u), x.dot(&q.v));
        if a >= -1e-9 && a <= q.size_m[0] + 1e-9 && b >= -1e-9 && b <= q.size_m[1] + 1e-9 {
            best = t;
        }
    }
    best
}

fn case(sc: Scenario, tx: f64, ty: f64) {
    let seed = sc.seed;
    let mut h = SimulatedHead::new(sc).unwrap();
    let e0 = h.encoders();
    let [w, hh] = h.scenario().image_size;
    let c = [(f64::from(w) - 1.0) / 2.0, (f64::from(hh) - 1.0) / 2.0];
    let (wl0, _) = h.world_from_cameras(&e0);
    let scene: Vec<Point3<f64>> = h.scene_points().iter().map(|(_, p)| *p).collect();
    let _ = &scene;
    let k = h.truth().left;
    let y = (ty - k.cy) / k.fy;
    let ray = nalgebra::Vector3::new((tx - k.cx - k.skew * y) / k.fx, y, 1.0);
    let o0 = Point3::from(wl0.translation.vector);
    let point = h.room().cast(&o0, &(wl0.rotation * ray)).unwrap();
    let start = [tx, ty];
    let o = Point3::from(wl0.translation.vector);
    let dir = (point - o).normalize();
    let dist = (point - o).norm();
    let hit = first_hit(&h, &o, &dir);
    let report = match fixate(&mut h, Camera::Left, start, &FixationOptions::default()) {
        Ok(r) => r,
        Err(e) => {
            println!("seed {seed} ({tx},{ty}): FAILED {e}");
            return;
        }
    };
    let enc = h.read_encoders().unwrap();
    let (wl, _) = h.world_from_cameras(&enc);
    let now = pixel_of(&h, &wl, &point).unwrap();
    let err = (now[0] - c[0]).hypot(now[1] - c[1]);
    // Placement: first step whose carried target is in view.
    let mut entry = String::new();
    for (i, s) in report.steps.iter().enumerate() {
        let (wl, _) = h.world_from_cameras(&s.encoders);
        let t = pixel_of(&h, &wl, &point).unwrap();
        let e = [s.target_px[0] - t[0], s.target_px[1] - t[1]];
        entry.push_str(&format!(
            " [{i}: ({:.0},{:.0}) e=({:+.2},{:+.2}) a=({:.0},{:.0})]",
            s.target_px[0], s.target_px[1], e[0], e[1], s.alpha_px[0], s.alpha_px[1]
        ));
    }
    println!(
        "seed {seed} ({tx},{ty}) start ({:.0},{:.0}) depth {dist:.2} hit {hit:.2}: err {err:.3} px ({:+.2},{:+.2}) moves {}\n   {entry}",
        start[0],
        start[1],
        now[0] - c[0],
        now[1] - c[1],
        report.steps.len()
    );
}

fn cases() -> Vec<(u64, f64, f64)> {
    let mut v = Vec::new();
    for seed in [1, 2, 3, 5] {
        for (tx, ty) in [(300.0, -150.0), (-150.0, 200.0)] {
            v.push((seed, tx, ty));
        }
    }
    v
}

#[test]
#[ignore]
fn diag_hard() {
    for (seed, tx, ty) in [
        (1u64, 450.0, 730.0),
        (6, -120.0, 640.0),
        (2, 300.0, -150.0),
        (3, 300.0, -150.0),
        (5, 300.0, -150.0),
        (5, -150.0, 200.0),
        (3, 900.0, 200.0),
        (2, 450.0, 730.0),
    ] {
        case(Scenario { seed, ..Scenario::default() }, tx, ty);
    }
}

#[test]
#[ignore]
fn diag_default() {
    for (seed, tx, ty) in cases() {
        case(Scenario { seed, ..Scenario::default() }, tx, ty);
    }
}

#[test]
#[ignore]
fn diag_pure_rotation() {
    for (seed, tx, ty) in cases() {
        case(
            Scenario {
                seed,
                camera_forward_offset_m: 0.0,
                elevation_below_cameras_m: 0.0,
                elevation_tilt_max_deg: 0.0,
                ..Scenario::default()
            },
            tx,
            ty,
        );
    }
}

#[test]
#[ignore]
fn diag_depths() {
    for seed in [1u64, 2, 3, 5] {
        let h = SimulatedHead::new(Scenario { seed, ..Scenario::default() }).unwrap();
        let e0 = h.encoders();
        let (wl0, _) = h.world_from_cameras(&e0);
        let k = h.truth().left;
        let o0 = Point3::from(wl0.translation.vector);
        let mut line = format!("seed {seed}:");
        for (tx, ty) in [
            (300.0, -150.0),
            (300.0, -100.0),
            (300.0, -50.0),
            (300.0, 0.0),
            (300.0, 50.0),
            (300.0, 100.0),
            (-150.0, 200.0),
            (-50.0, 200.0),
            (50.0, 200.0),
            (150.0, 200.0),
        ] {
            let y = (ty - k.cy) / k.fy;
            let ray = nalgebra::Vector3::new((tx - k.cx) / k.fx, y, 1.0);
            let p = h.room().cast(&o0, &(wl0.rotation * ray)).unwrap();
            let q = wl0.inverse() * p;
            line.push_str(&format!(" ({tx},{ty}):z={:.2}", q.z));
        }
        println!("{line}");
    }
}
