//! A phone pose with a non-unit quaternion is a refused command (issue 12): it is named in
//! `TeleopFeedback.error`, counted in `commands_rejected` and shown as the `REJECTED_INVALID` verdict, and it
//! moves nothing.

use phone2act_sdk::TeleopOptions;
use phone2act_sdk::buttons;
use phone2act_sdk::proto as v1;
use phone2act_tests::{TestServer, default_config, pos};
use std::time::Duration;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_non_unit_quaternion_is_counted_and_shown_as_rejected_invalid() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(default_config(dir.path())).await.unwrap();
    let client = server.client().await.unwrap();
    tokio::time::sleep(Duration::from_millis(400)).await;
    let mut phone = client.teleop("main", TeleopOptions::default()).await.unwrap();
    let origin = v1::Pose::from_parts([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]);
    let seq = phone
        .send_pose(origin, vec![buttons::clutch_engage()], 0)
        .await
        .unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    let state = fb.arm_state.unwrap();
    assert!(state.engaged);
    let rejected_before = state.commands_rejected;
    let target_before = pos(state.robot_from_target.as_ref().unwrap());

    // |q| = 2: not a rotation.
    let bad = v1::Pose::from_parts([0.01, 0.0, 0.0], [0.0, 0.0, 0.0, 2.0]);
    let seq = phone.send_pose(bad, vec![], 0).await.unwrap();
    let fb = phone.feedback_for(seq).await.unwrap();
    assert!(fb.error.contains("quaternion"), "{}", fb.error);
    let state = fb.arm_state.unwrap();
    assert_eq!(state.commands_rejected, rejected_before + 1);
    let decision = state.last_decision.unwrap();
    assert_eq!(
        decision.verdict(),
        v1::GateVerdict::RejectedInvalid,
        "{decision:?}"
    );
    assert!(
        decision.reason.contains("invalid phone pose"),
        "{}",
        decision.reason
    );
    // Nothing was commanded: the target is bit for bit the one before.
    let target_after = pos(state.robot_from_target.as_ref().unwrap());
    assert!(
        target_after
            .iter()
            .zip(target_before)
            .all(|(a, b)| a.to_bits() == b.to_bits())
    );
    drop(phone);
    server.shutdown().await.unwrap();
}
