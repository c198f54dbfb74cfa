//! A minimal remote policy: takes control of an arm, waits for an observation, and answers it with a
//! 10-step chunk that moves the end effector 3 cm along +x (delta actions relative to the observed pose).
//!
//! `cargo run -p phone2act-sdk --example policy_chunk -- [URL] [ARM]`

use phone2act_sdk::proto as v1;
use std::time::Duration;

#[tokio::main(flavor = "current_thread")]
async fn main() -> Result<(), phone2act_sdk::Error> {
    let mut args = std::env::args().skip(1);
    let url = args.next().unwrap_or_else(|| "http://127.0.0.1:50051".to_owned());
    let arm = args.next().unwrap_or_else(|| "main".to_owned());
    let client = phone2act_sdk::Client::connect(&url, None).await?;
    let mut session = client
        .policy(v1::PolicyHello {
            arms: vec![arm.clone()],
            observation_rate_hz: 10.0,
            image_encoding: v1::ImageEncoding::None as i32,
            request_control: true,
            policy_name: "example".into(),
            silence_timeout_s: 2.0,
            ..v1::PolicyHello::default()
        })
        .await?;
    let names = &session.ready().arms[0].action_names;
    println!("controlling {arm}; actions are [{}]", names.join(", "));
    let obs = session.next_observation().await?;
    let steps = (1..=10)
        .map(|k| v1::ActionStep {
            values: vec![0.003 * f64::from(k), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        })
        .collect();
    let chunk = v1::ActionChunk {
        arm: arm.clone(),
        steps,
        step_period_s: 0.05,
        observation_id: obs.observation_id,
        mode: v1::ActionMode::DeltaEe as i32,
        blend_steps: 0,
        keep_steps: 0,
    };
    let accepted = session.push_chunk_checked(&client, chunk).await?;
    println!(
        "chunk accepted: {} steps scheduled, {} already past",
        accepted.steps_scheduled, accepted.steps_skipped
    );
    tokio::time::sleep(Duration::from_millis(700)).await;
    session.release().await?;
    Ok(())
}
