//! Point-mode sessions (`headalign demo --session DIR` without `--images`): the verge/tilt
//! stage's captures are recorded as they happen (`NN-name/view.json` with the tracked
//! points in its `capture` member, no images; `events.jsonl`), the views so far as an
//! observation session (`observations.json`, format `headalign-observations/1`, readable
//! by `align --observations`) and the demo's JSON as `report.json`. The robot stages
//! that follow are recorded too (their captures in folders named by
//! stage, drives and steering as events, the stage plan in `session.json` `stages`), and
//! `replay` re-runs the verge/tilt stage and then those stages. The recording is
//! [`headalign_io::runs`]' (`verge_tilt_points`, `robot_stages_points`); here are the
//! session's description and the options it was recorded with.

use headalign::procedure::{AutoRotation, VergeTiltOptions};
use headalign_io::session::SessionInfo;

/// The session description of a point-mode run.
pub fn session_info(
    options: &VergeTiltOptions,
    image_size: [u32; 2],
    head: serde_json::Value,
) -> SessionInfo {
    let mut info = SessionInfo::new(
        headalign_io::runs::PROCEDURE_POINTS,
        options.rotation_deg,
        options.estimation.seed,
        image_size,
    );
    info.auto_rotation = options.auto_rotation.is_some();
    info.head = head;
    info
}

/// The options a point-mode session was recorded with.
pub fn options(info: &SessionInfo) -> VergeTiltOptions {
    VergeTiltOptions {
        rotation_deg: info.rotation_deg,
        verge_rotation_deg: info.rotation_deg,
        auto_rotation: info.auto_rotation.then(AutoRotation::default),
        estimation: headalign::verge_tilt::EstimationOptions {
            seed: info.estimation_seed,
            ..headalign::verge_tilt::EstimationOptions::default()
        },
        ..VergeTiltOptions::default()
    }
}
