use headalign::estimate::EstimationOptions;
use headalign::frontend::{FrontEndOptions, TrackingHead};
use headalign::imaging::{VergingOptions, verge_to_common_view};
use headalign::procedure::{VergeTiltOptions, VergeTiltRun};
use headalign_sim::{Scenario, SimulatedHead, calibration_errors};
use std::time::Instant;

fn main() {
    let seeds: Vec<u64> = std::env::args().skip(1).map(|s| s.parse().unwrap()).collect();
    for seed in seeds {
        let t0 = Instant::now();
        let mut head = SimulatedHead::new(Scenario { seed, ..Scenario::default() }).unwrap();
        let vr = verge_to_common_view(&mut head, &VergingOptions::default());
        println!("seed {seed}: verging {:?}", vr.as_ref().map(|r| r.steps.iter().map(|s| (s.shift_px[0], s.verge_right_move_deg)).collect::<Vec<_>>()));
        let before = head.alignment_errors(&head.encoders());
        let mut th = TrackingHead::new(&mut head, FrontEndOptions::default()).unwrap();
        let options = VergeTiltOptions { estimation: EstimationOptions { seed, ..EstimationOptions::default() }, ..VergeTiltOptions::default() };
        let mut run = VergeTiltRun::default();
        let out = run.run(&mut th, &options);
        for t in &th.tracking { println!("   {t:?}"); }
        drop(th);
        match out {
            Ok(o) => {
                let after = head.alignment_errors(&head.encoders());
                let st = &o.calibration.bundle.state;
                let t = head.truth().clone();
                let cal = calibration_errors(&t.left, &t.right, &st.left, &st.right);
                println!("   before {before:?}\n   after {after:?}\n   f_err {:.3} % rms {:.3} px obs {} t {:.1}s", cal.f_err_pct, o.calibration.report.final_rms_px, o.calibration.report.bundle_observations, t0.elapsed().as_secs_f64());
            }
            Err(e) => println!("   FAILED {e}"),
        }
    }
}
