//! Records one episode on a running server, stops (saves) it and lists the dataset.
//!
//! `cargo run -p phone2act-sdk --example record_episode -- [URL] [TASK]`

use std::time::Duration;

#[tokio::main(flavor = "current_thread")]
async fn main() -> Result<(), phone2act_sdk::Error> {
    let mut args = std::env::args().skip(1);
    let url = args.next().unwrap_or_else(|| "http://127.0.0.1:50051".to_owned());
    let task = args
        .next()
        .unwrap_or_else(|| "put the ball in the basket".to_owned());
    let client =
        phone2act_sdk::Client::connect(&url, std::env::var("PHONE2ACT_TOKEN").ok().as_deref()).await?;
    let mut episodes = client.episodes();
    let status = episodes.start(&task).await?;
    println!("recording episode {} ({task})", status.episode_index);
    // A phone or a policy would drive the arm here.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let saved = episodes.stop().await?;
    let ep = saved.episode.unwrap_or_default();
    println!(
        "saved episode {}: {} frames in {:.0} ms",
        ep.episode_index,
        ep.length_frames,
        saved.save_latency_s * 1e3
    );
    for ep in episodes.list().await?.episodes {
        println!(
            "{:>4} {:>6} frames  {}",
            ep.episode_index, ep.length_frames, ep.task
        );
    }
    Ok(())
}
