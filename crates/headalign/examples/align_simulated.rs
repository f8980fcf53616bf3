//! Align a simulated head with the verge/tilt procedure, in about 20 lines.
//!
//! Teaches the library's main call: build a head (here the simulator's default one from
//! `headalign-sim`: 200 scene points, 1 px image noise, 10 % outliers, unknown encoder
//! zeros and mounting errors), run [`VergeTiltRun::run`] on it, and read the outcome: the
//! encoder readings at which the head is aligned, each with its 1-sigma uncertainty. The
//! procedure captures views at small elevation, pan and vergence turns, self-calibrates
//! the cameras from them, computes the aligned readings, moves there and checks the result
//! by vision. The simulator knows the truth, so the example also prints each reading's
//! error and the cameras' remaining alignment errors.
//!
//! `cargo run --release -p headalign --example align_simulated` (about a second).

use headalign::procedure::{VergeTiltOptions, VergeTiltRun};
use headalign_sim::{Scenario, SimulatedHead};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // The head: any `headalign::StereoHead` (see `custom_head.rs` for your own).
    let mut head = SimulatedHead::new(Scenario::default())?;
    let before = head.alignment_errors(&head.encoders());

    // The procedure: capture, self-calibrate, solve, move to the aligned readings, check.
    let outcome = VergeTiltRun::default().run(&mut head, &VergeTiltOptions::default())?;

    let (aligned, sigma, truth) =
        (outcome.solution.aligned_encoders, outcome.sigmas, head.aligned_encoders());
    println!("{:<12} {:>10} {:>8} {:>10}", "reading", "aligned", "sigma", "error");
    for (name, est, sig, true_deg) in [
        ("elevation", aligned.elevation, sigma.elevation_deg, truth.elevation),
        ("verge left", aligned.verge_left, sigma.verge_left_deg, truth.verge_left),
        ("verge right", aligned.verge_right, sigma.verge_right_deg, truth.verge_right),
    ] {
        println!("{name:<12} {est:>10.3} {sig:>8.3} {:>+10.3}   deg", est - true_deg);
    }

    // The head is now at the aligned readings: the cameras' true remaining errors.
    let after = head.alignment_errors(&head.encoders());
    println!("\nalignment error (deg)   before    after");
    for (name, b, a) in [
        ("verge left", before.verge_err_l_deg, after.verge_err_l_deg),
        ("verge right", before.verge_err_r_deg, after.verge_err_r_deg),
        ("elevation left", before.elev_err_l_deg, after.elev_err_l_deg),
    ] {
        println!("{name:<20} {b:>+8.3} {a:>+8.3}");
    }
    Ok(())
}
