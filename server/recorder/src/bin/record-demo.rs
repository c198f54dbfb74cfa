//! Records episodes from synthetic test-pattern cameras and a synthetic robot. Used by the kill test and
//! as a smoke test of the whole recorder: prints one line per event on stdout (`started N`, `stopping N`,
//! `saved N <frames> <save_ms>`) so a supervising test can time a SIGKILL.
//!
//! Usage: record-demo ROOT [--format v30|v21] [--episodes N] [--seconds S] [--fps F] [--cameras K]
//!                         [--size WxH] [--codec C] [--task TEXT]

use phone2act_capture::camera::{FrameSlot, spawn_test_pattern};
use phone2act_dataset::{CameraSpec, DatasetSpec, Format};
use phone2act_recorder::Recorder;
use phone2act_recorder::synthetic::SyntheticRobot;
use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

fn main() {
    if let Err(e) = run() {
        eprintln!("record-demo: {e}");
        std::process::exit(1);
    }
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let root = PathBuf::from(args.next().ok_or("usage: record-demo ROOT [options]")?);
    let (mut format, mut episodes, mut seconds, mut fps, mut ncams) =
        (Format::V30, 3u64, 1.0f64, 20u32, 2usize);
    let (mut w, mut h, mut codec, mut task) = (64u32, 48u32, None, "pick the red cube".to_owned());
    while let Some(flag) = args.next() {
        let mut val = || args.next().ok_or_else(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--format" => format = if val()? == "v21" { Format::V21 } else { Format::V30 },
            "--episodes" => episodes = val()?.parse()?,
            "--seconds" => seconds = val()?.parse()?,
            "--fps" => fps = val()?.parse()?,
            "--cameras" => ncams = val()?.parse()?,
            "--size" => {
                let v = val()?;
                let (a, b) = v.split_once('x').ok_or("--size WxH")?;
                (w, h) = (a.parse()?, b.parse()?);
            }
            "--codec" => codec = Some(val()?),
            "--task" => task = val()?,
            other => return Err(format!("unknown option {other}").into()),
        }
    }
    let names = ["front", "wrist", "side", "top"];
    let mut cams = Vec::new();
    let mut threads = Vec::new();
    let mut specs = Vec::new();
    for name in names.iter().take(ncams) {
        let slot = Arc::new(FrameSlot::default());
        threads.push(spawn_test_pattern(name, w, h, f64::from(fps), Arc::clone(&slot))?);
        cams.push(((*name).to_owned(), slot));
        specs.push(CameraSpec {
            name: (*name).to_owned(),
            width: w,
            height: h,
        });
    }
    let spec = DatasetSpec {
        root,
        format,
        fps,
        robot_type: "phone2act_sim".into(),
        video_codec: codec,
        state_names: SyntheticRobot::state_names(),
        action_names: SyntheticRobot::action_names(),
        cameras: specs,
        modality: SyntheticRobot::modality(),
        success: false,
        intervention: false,
        provenance: serde_json::json!({"source": "record-demo"}),
    };
    let rec = Recorder::open(spec, Arc::new(SyntheticRobot), cams)?;
    let out = std::io::stdout();
    let say = |s: String| {
        let mut o = out.lock();
        let _ = writeln!(o, "{s}");
        let _ = o.flush();
    };
    let first = rec.status().episodes_saved;
    for i in 0..episodes {
        let t = if i % 2 == 0 {
            task.clone()
        } else {
            format!("{task} again")
        };
        let st = rec.start_episode(&t)?;
        say(format!("started {}", st.episode_index));
        std::thread::sleep(Duration::from_secs_f64(seconds));
        // On a busy machine a short episode can end before its first frame is in; an episode without frames is
        // not saved, so wait for one (up to 10 s) rather than end the run.
        let waited = std::time::Instant::now();
        while rec.status().frames_recorded == 0 && waited.elapsed() < Duration::from_secs(10) {
            std::thread::sleep(Duration::from_millis(5));
        }
        say(format!("stopping {}", st.episode_index));
        let s = rec.stop_episode()?;
        say(format!(
            "saved {} {} {:.1} dropped={}",
            s.index,
            s.length_frames,
            s.save_latency_s * 1e3,
            s.dropped_frames
        ));
    }
    say(format!("done {episodes} episodes (first {first})"));
    rec.close()?;
    Ok(())
}
