//! `phone2act dataset plot DIR --episode N`: one self-contained HTML page of an episode. A strip of camera
//! frames (evenly spaced, decoded from the episode's videos, inline JPEG), then one panel per state and per
//! action dimension over time (inline SVG drawn by plotters; the measured state and the commanded action of
//! the same quantity share a panel), with the operator's clutch (engaged spans shaded) and the safety gate's
//! rejections and clamps marked, from the events sidecar phone2act writes beside each episode.

use anyhow::Context as _;
use base64::Engine as _;
use phone2act_dataset::events::{EpisodeEvent, EventKind, events_path, read_events};
use phone2act_dataset::readback::{Episode, read_episode};
use plotters::prelude::*;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Camera frames shown per camera (fewer for a shorter episode).
const FRAMES_PER_CAMERA: usize = 5;
/// Width of a frame in the strip, px: enough to recognise the scene, small enough for a light page.
const FRAME_WIDTH_PX: u32 = 240;
const PANEL_SIZE_PX: (u32, u32) = (560, 190);
const STATE_COLOR: RGBColor = RGBColor(31, 119, 180);
const ACTION_COLOR: RGBColor = RGBColor(255, 127, 14);
const ENGAGED_COLOR: RGBColor = RGBColor(44, 160, 44);
const REJECTED_COLOR: RGBColor = RGBColor(214, 39, 40);
const CLAMPED_COLOR: RGBColor = RGBColor(188, 128, 189);
/// Late frames and pauses of the recorder's timeline.
const TIMELINE_COLOR: RGBColor = RGBColor(120, 120, 120);
/// Robot warnings (a servo alarm while the arm keeps working) and their clearing.
const WARNING_COLOR: RGBColor = RGBColor(230, 150, 0);
/// A policy starting or stopping to drive an arm.
const POLICY_COLOR: RGBColor = RGBColor(23, 190, 207);

/// One panel: a state dimension, an action dimension, or both when they name the same quantity.
#[derive(Debug, PartialEq, Eq)]
struct Panel {
    title: String,
    state: Option<usize>,
    action: Option<usize>,
}

/// What a dimension's name says it measures, so that the measured and the commanded value meet: phone2act
/// names the measured end-effector pose `ee_x` … and the commanded target `x` … (per arm `left_ee_x`,
/// `left_x`); lerobot uses the same name for both (`shoulder_pan.pos`).
fn quantity(name: &str) -> String {
    name.split('_')
        .filter(|s| *s != "ee")
        .collect::<Vec<_>>()
        .join("_")
}

/// Panels in the state's order, each action dimension beside the state dimension of the same quantity, the
/// others after.
fn panels(state: &[String], action: &[String]) -> Vec<Panel> {
    let mut used = vec![false; action.len()];
    let mut out: Vec<Panel> = state
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let matched = action
                .iter()
                .enumerate()
                .position(|(j, a)| !used[j] && quantity(a) == quantity(s));
            if let Some(j) = matched {
                used[j] = true;
            }
            let title = match matched {
                Some(j) if action[j] != *s => format!("{s} / {}", action[j]),
                _ => s.clone(),
            };
            Panel {
                title,
                state: Some(i),
                action: matched,
            }
        })
        .collect();
    out.extend(
        action
            .iter()
            .enumerate()
            .filter(|(j, _)| !used[*j])
            .map(|(j, a)| Panel {
                title: a.clone(),
                state: None,
                action: Some(j),
            }),
    );
    out
}

/// The unit of a dimension of a phone2act dataset, from its one layout definition
/// (`phone2act_core::layout`): positions in m, rotation-matrix entries without unit, the gripper 0 (open) to
/// 1 (closed), joints in rad; lerobot's SO-101 layout (`*.pos`) in degrees and the gripper in percent.
/// Another writer's units are not recorded anywhere, so they are not guessed.
fn unit(name: &str, written_by_phone2act: bool) -> &'static str {
    if !written_by_phone2act {
        return "unit not recorded";
    }
    let last = name.rsplit('_').next().unwrap_or(name);
    // lerobot's motor features are `<motor>.pos`.
    let motor = name.strip_suffix(".pos");
    if motor.is_some_and(|m| m.ends_with("gripper")) {
        "%"
    } else if motor.is_some() {
        "deg"
    } else if last == "gripper" {
        "0 open … 1 closed"
    } else if matches!(last, "x" | "y" | "z") {
        "m"
    } else if last.len() == 3
        && last.starts_with('r')
        && last[1..].bytes().all(|b| (b'0'..=b'2').contains(&b))
    {
        "rotation matrix entry"
    } else {
        "rad"
    }
}

/// Clutch-engaged spans of `arm`, in s: from each engage to the next release (or the episode's end).
fn engaged_spans(events: &[EpisodeEvent], end_s: f64) -> Vec<(String, f64, f64)> {
    let mut open: Vec<(String, f64)> = Vec::new();
    let mut spans = Vec::new();
    for e in events {
        match e.kind {
            EventKind::ClutchEngage => open.push((e.arm.clone(), e.timestamp)),
            EventKind::ClutchRelease => {
                if let Some(i) = open.iter().position(|(a, _)| *a == e.arm) {
                    let (arm, from) = open.remove(i);
                    spans.push((arm, from, e.timestamp));
                }
            }
            EventKind::GateRejected
            | EventKind::GateClamped
            | EventKind::JointLimited
            | EventKind::LateTick
            | EventKind::Paused
            | EventKind::RobotWarning
            | EventKind::RobotWarningCleared
            | EventKind::PolicyStart
            | EventKind::PolicyStop
            | EventKind::PolicyResume => {}
        }
    }
    spans.extend(open.into_iter().map(|(arm, from)| (arm, from, end_s)));
    spans
}

/// The points of one series, at most two per bucket of consecutive frames (its lowest and its highest, in
/// time order), so that an hour-long episode's panel stays a few kB and still shows every spike.
fn decimate(times_s: &[f64], values: &[f64], buckets: usize) -> Vec<(f64, f64)> {
    let points: Vec<(f64, f64)> = times_s
        .iter()
        .zip(values)
        .filter(|(_, v)| v.is_finite())
        .map(|(t, v)| (*t, *v))
        .collect();
    if points.len() <= 2 * buckets {
        return points;
    }
    let per_bucket = points.len().div_ceil(buckets);
    let mut out = Vec::with_capacity(2 * buckets);
    for chunk in points.chunks(per_bucket) {
        let by_value = |a: &&(f64, f64), b: &&(f64, f64)| a.1.total_cmp(&b.1);
        let (Some(lo), Some(hi)) = (chunk.iter().min_by(by_value), chunk.iter().max_by(by_value)) else {
            continue;
        };
        let (first, second) = if lo.0 <= hi.0 { (lo, hi) } else { (hi, lo) };
        out.push(*first);
        if second != first {
            out.push(*second);
        }
    }
    out
}

/// The arm a dimension belongs to, among the arms that have events: with several arms phone2act prefixes
/// every name with `{arm}_`. `None` (a single arm's unprefixed names, another writer's): every arm's.
fn arm_of<'a>(name: &str, arms: &[&'a str]) -> Option<&'a str> {
    arms.iter()
        .copied()
        .find(|arm| name.strip_prefix(arm).is_some_and(|rest| rest.starts_with('_')))
}

fn html_escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// One panel's SVG.
fn panel_svg(
    times_s: &[f64],
    series: &[(&[f64], RGBColor)],
    events: &[EpisodeEvent],
    spans: &[(String, f64, f64)],
    y_desc: &str,
) -> anyhow::Result<String> {
    let end_s = times_s.last().copied().unwrap_or(0.0).max(1e-3);
    let values = series
        .iter()
        .flat_map(|(v, _)| v.iter().copied())
        .filter(|v| v.is_finite());
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    let (lo, hi) = if lo.is_finite() { (lo, hi) } else { (0.0, 1.0) };
    // A constant signal gets a band around it rather than a zero-height axis.
    let pad = ((hi - lo) * 0.08).max(1e-3 * hi.abs().max(1.0));
    let (y0, y1) = (lo - pad, hi + pad);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, PANEL_SIZE_PX).into_drawing_area();
        root.fill(&WHITE)?;
        let mut chart = ChartBuilder::on(&root)
            .margin(6)
            .x_label_area_size(30)
            .y_label_area_size(62)
            .build_cartesian_2d(0.0..end_s, y0..y1)?;
        chart
            .configure_mesh()
            .x_desc("t [s]")
            .y_desc(y_desc)
            .x_labels(8)
            .y_labels(5)
            .light_line_style(WHITE.mix(0.0))
            .label_style(("sans-serif", 11))
            .draw()?;
        chart.draw_series(spans.iter().map(|(_, from, to)| {
            Rectangle::new([(*from, y0), (*to, y1)], ENGAGED_COLOR.mix(0.13).filled())
        }))?;
        // One line per kind and pixel column: a gate refusing every frame of an hour must not draw 70 000.
        let mut drawn = std::collections::BTreeSet::new();
        for e in events {
            let column = (e.timestamp / end_s * f64::from(PANEL_SIZE_PX.0)).round() as i64;
            if !drawn.insert((e.kind as u8, column)) {
                continue;
            }
            let color = match e.kind {
                EventKind::GateRejected => REJECTED_COLOR,
                // Both shorten a command: the gate in task space, the joint limits in joint space.
                EventKind::GateClamped | EventKind::JointLimited => CLAMPED_COLOR,
                EventKind::ClutchEngage | EventKind::ClutchRelease => ENGAGED_COLOR,
                // The recorder's timeline: frames that are not at their own time, and where time jumps.
                EventKind::LateTick | EventKind::Paused => TIMELINE_COLOR,
                EventKind::RobotWarning | EventKind::RobotWarningCleared => WARNING_COLOR,
                EventKind::PolicyStart | EventKind::PolicyStop | EventKind::PolicyResume => POLICY_COLOR,
            };
            chart.draw_series(std::iter::once(PathElement::new(
                vec![(e.timestamp, y0), (e.timestamp, y1)],
                color.stroke_width(if e.kind == EventKind::GateRejected { 2 } else { 1 }),
            )))?;
        }
        for (values, color) in series {
            let points = decimate(times_s, values, PANEL_SIZE_PX.0 as usize);
            chart.draw_series(LineSeries::new(points, color.stroke_width(2)))?;
        }
        root.present()?;
    }
    Ok(svg)
}

/// The camera strip: per camera, evenly spaced frames of the episode as inline JPEGs.
fn camera_strip(episode: &Episode, out: &mut String) -> anyhow::Result<usize> {
    let frames = episode.frame_index.len();
    let count = FRAMES_PER_CAMERA.min(frames);
    let picks: Vec<usize> = (0..count)
        .map(|k| {
            if count > 1 {
                k * (frames - 1) / (count - 1)
            } else {
                0
            }
        })
        .collect();
    let mut images = 0;
    out.push_str("<section id=\"cameras\"><h2>Cameras</h2>\n");
    if episode.videos.is_empty() {
        out.push_str("<p class=\"note\">This dataset has no camera (no video feature).</p>\n");
    }
    for video in &episode.videos {
        let times: Vec<f64> = picks
            .iter()
            .map(|&i| video.from_s + episode.frame_index[i] as f64 / episode.fps)
            .collect();
        let decoded = phone2act_dataset::av::decode::frames_at(&video.path, &times, FRAME_WIDTH_PX)
            .with_context(|| format!("cannot read the frames of camera {}", video.key))?;
        let _ = writeln!(
            out,
            "<div class=\"camera\" data-key=\"{0}\"><h3>{0}</h3><div class=\"strip\">",
            html_escape(&video.key)
        );
        for (&i, frame) in picks.iter().zip(&decoded) {
            let jpeg = phone2act_capture::jpeg::encode_jpeg(&frame.rgb, frame.width, frame.height, 85)
                .context("cannot encode a frame as JPEG")?;
            let frame_index = episode.frame_index[i];
            let _ = writeln!(
                out,
                "<figure class=\"frame\" data-frame=\"{frame_index}\"><img alt=\"{} frame {frame_index}\" width=\"{}\" height=\"{}\" src=\"data:image/jpeg;base64,{}\"><figcaption>frame {frame_index} · {:.2} s</figcaption></figure>",
                html_escape(&video.key),
                frame.width,
                frame.height,
                base64::engine::general_purpose::STANDARD.encode(jpeg),
                frame_index as f64 / episode.fps
            );
            images += 1;
        }
        out.push_str("</div></div>\n");
    }
    out.push_str("</section>\n");
    Ok(images)
}

/// Writes the page for episode `index` of the dataset at `root` to `out` (default: `episode_NNNNNN.html`
/// in the current directory, never inside the dataset, which lerobot would then upload). Returns the path.
pub(crate) fn plot(root: &Path, index: u64, out: Option<PathBuf>) -> anyhow::Result<PathBuf> {
    let episode = read_episode(root, index)?;
    let events = read_events(root, index)?;
    let written_by_phone2act = root.join(phone2act_dataset::dataset::PROVENANCE_FILE).is_file();
    let times_s: Vec<f64> = episode
        .frame_index
        .iter()
        .map(|&f| f as f64 / episode.fps)
        .collect();
    let end_s = times_s.last().copied().unwrap_or(0.0);
    let (marks, spans) = match &events {
        Some(e) => (e.clone(), engaged_spans(e, end_s)),
        None => (Vec::new(), Vec::new()),
    };
    let mut arms: Vec<&str> = marks.iter().map(|e| e.arm.as_str()).collect();
    arms.sort_unstable();
    arms.dedup();
    let vector = |key: &str| episode.vectors.iter().find(|v| v.key == key);
    let (state, action) = (vector("observation.state"), vector("action"));
    let names = |v: Option<&phone2act_dataset::readback::VectorFeature>| {
        v.map(|v| v.names.clone()).unwrap_or_default()
    };
    let column = |v: &phone2act_dataset::readback::VectorFeature, i: usize| -> Vec<f64> {
        v.rows
            .iter()
            .map(|r| r.get(i).copied().unwrap_or(f64::NAN))
            .collect()
    };

    let mut html = String::new();
    let title = format!(
        "{} episode {index}",
        root.file_name().map_or_else(
            || root.display().to_string(),
            |n| n.to_string_lossy().into_owned()
        )
    );
    let _ = write!(
        html,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{}</title>\n<style>{STYLE}</style></head><body>\n<h1>{}</h1>\n<p class=\"facts\">LeRobot {} · robot {} · {} frames at {} fps ({:.2} s) · task “{}”</p>\n",
        html_escape(&title),
        html_escape(&title),
        html_escape(&episode.version),
        html_escape(if episode.robot_type.is_empty() {
            "?"
        } else {
            &episode.robot_type
        }),
        episode.frame_index.len(),
        episode.fps,
        end_s,
        html_escape(&episode.task),
    );
    let frames = camera_strip(&episode, &mut html)?;

    html.push_str("<section id=\"events\"><h2>Clutch and gate events</h2>\n");
    match &events {
        None => {
            let _ = writeln!(
                html,
                "<p class=\"note\" id=\"no-events\">No events recorded: this dataset has no {} (it was written by lerobot or by a phone2act older than the events sidecar), so the plots carry no clutch or gate markers.</p>",
                events_path(index).display()
            );
        }
        Some(list) => {
            let _ = writeln!(
                html,
                "<p class=\"legend\"><span class=\"key engaged\"></span>clutch engaged <span class=\"key rejected\"></span>gate rejected <span class=\"key clamped\"></span>gate clamped · {} events from {}</p>\n<ol class=\"events\">",
                list.len(),
                events_path(index).display()
            );
            for e in list {
                let _ = writeln!(
                    html,
                    "<li class=\"event\" data-kind=\"{kind}\" data-frame=\"{}\" data-arm=\"{}\">frame {} · {:.2} s · arm {} · {kind}{}{}</li>",
                    e.frame_index,
                    html_escape(&e.arm),
                    e.frame_index,
                    e.timestamp,
                    html_escape(&e.arm),
                    if e.count > 1 {
                        format!(" ×{}", e.count)
                    } else {
                        String::new()
                    },
                    if e.detail.is_empty() {
                        String::new()
                    } else {
                        format!(": {}", html_escape(&e.detail))
                    },
                    kind = serde_json::to_value(e.kind)
                        .ok()
                        .and_then(|v| v.as_str().map(str::to_owned))
                        .unwrap_or_default(),
                );
            }
            html.push_str("</ol>\n");
        }
    }
    html.push_str("</section>\n<section id=\"panels\"><h2>State and action</h2>\n<p class=\"legend\"><span class=\"key state\"></span>observation.state (measured) <span class=\"key action\"></span>action (commanded, after the safety gate)</p>\n<div class=\"grid\">\n");
    let layout = panels(&names(state), &names(action));
    for (n, panel) in layout.iter().enumerate() {
        let mut series: Vec<(Vec<f64>, RGBColor)> = Vec::new();
        let mut units = Vec::new();
        if let (Some(i), Some(v)) = (panel.state, state) {
            series.push((column(v, i), STATE_COLOR));
            units.push(unit(&v.names[i], written_by_phone2act));
        }
        if let (Some(j), Some(v)) = (panel.action, action) {
            series.push((column(v, j), ACTION_COLOR));
            units.push(unit(&v.names[j], written_by_phone2act));
        }
        units.dedup();
        let units = units.join(" / ");
        let refs: Vec<(&[f64], RGBColor)> = series.iter().map(|(v, c)| (v.as_slice(), *c)).collect();
        // A bimanual dataset: each arm's panels carry that arm's clutch and gate marks only.
        let name = panel.title.split(" / ").next().unwrap_or_default();
        let arm = arm_of(name, &arms);
        let ours = |a: &str| arm.is_none_or(|arm| arm == a);
        let panel_marks: Vec<EpisodeEvent> = marks.iter().filter(|e| ours(&e.arm)).cloned().collect();
        let panel_spans: Vec<(String, f64, f64)> = spans.iter().filter(|s| ours(&s.0)).cloned().collect();
        let svg = panel_svg(&times_s, &refs, &panel_marks, &panel_spans, &units)
            .with_context(|| format!("cannot draw the panel of {}", panel.title))?;
        let attr = |v: Option<&phone2act_dataset::readback::VectorFeature>, i: Option<usize>| {
            i.and_then(|i| Some(html_escape(&v?.names[i])))
                .unwrap_or_default()
        };
        let _ = writeln!(
            html,
            "<figure class=\"panel\" id=\"panel-{n}\" data-state=\"{}\" data-action=\"{}\"><figcaption>{} [{}]</figcaption>{svg}</figure>",
            attr(state, panel.state),
            attr(action, panel.action),
            html_escape(&panel.title),
            html_escape(&units),
        );
    }
    html.push_str("</div></section>\n</body></html>\n");

    let out = out.unwrap_or_else(|| PathBuf::from(format!("episode_{index:06}.html")));
    std::fs::write(&out, html).with_context(|| format!("cannot write {}", out.display()))?;
    tracing::debug!(panels = layout.len(), frames, "plot written");
    Ok(out)
}

const STYLE: &str = "body{font-family:sans-serif;margin:16px;color:#222}h1{font-size:20px;margin:0 0 4px}\
h2{font-size:16px;margin:18px 0 6px}h3{font-size:13px;margin:6px 0}.facts,.note,.legend{font-size:13px}\
.note{color:#8a5a00}.strip{display:flex;gap:6px;flex-wrap:wrap}figure{margin:0}\
.frame figcaption{font-size:11px;color:#555}.grid{display:grid;grid-template-columns:repeat(auto-fill,minmax(560px,1fr));gap:8px}\
.panel figcaption{font-size:13px;font-weight:bold}.events{font-size:12px;columns:2}\
.key{display:inline-block;width:14px;height:10px;margin:0 4px 0 10px;vertical-align:middle}\
.key.state{background:#1f77b4}.key.action{background:#ff7f0e}.key.engaged{background:rgba(44,160,44,.3)}\
.key.rejected{background:#d62728}.key.clamped{background:#bc80bd}";

#[cfg(test)]
mod tests {
    use super::*;

    fn strings(names: &[&str]) -> Vec<String> {
        names.iter().map(|s| (*s).to_owned()).collect()
    }

    #[test]
    fn measured_and_commanded_quantities_share_a_panel() {
        let state = strings(&["j0", "ee_x", "ee_r00", "gripper"]);
        let action = strings(&["x", "r00", "gripper", "extra"]);
        let got: Vec<(Option<usize>, Option<usize>)> = panels(&state, &action)
            .iter()
            .map(|p| (p.state, p.action))
            .collect();
        assert_eq!(
            got,
            [
                (Some(0), None),
                (Some(1), Some(0)),
                (Some(2), Some(1)),
                (Some(3), Some(2)),
                (None, Some(3))
            ]
        );
        assert_eq!(panels(&state, &action)[1].title, "ee_x / x");
        // Per arm: left_ee_x meets left_x, not right_x.
        let p = panels(
            &strings(&["left_ee_x", "right_ee_x"]),
            &strings(&["right_x", "left_x"]),
        );
        assert_eq!((p[0].action, p[1].action), (Some(1), Some(0)));
        // lerobot: the same name on both sides.
        let p = panels(&strings(&["shoulder_pan.pos"]), &strings(&["shoulder_pan.pos"]));
        assert_eq!((p.len(), p[0].title.as_str()), (1, "shoulder_pan.pos"));
    }

    #[test]
    fn units_follow_the_layout_and_are_not_guessed_for_others() {
        assert_eq!(unit("left_ee_z", true), "m");
        assert_eq!(unit("r21", true), "rotation matrix entry");
        assert_eq!(unit("shoulder_lift", true), "rad");
        assert_eq!(unit("gripper.pos", true), "%");
        assert_eq!(unit("elbow_flex.pos", true), "deg");
        assert_eq!(unit("j0", false), "unit not recorded");
    }

    #[test]
    fn decimation_keeps_every_spike_in_time_order() {
        let times: Vec<f64> = (0..100_000).map(|i| f64::from(i) / 30.0).collect();
        let mut values: Vec<f64> = times.iter().map(|t| (t * 0.1).sin()).collect();
        values[77_777] = 9.0;
        values[12_345] = -9.0;
        values[5] = f64::NAN;
        let points = decimate(&times, &values, 500);
        assert!(points.len() <= 1000, "{}", points.len());
        assert!(points.windows(2).all(|w| w[0].0 < w[1].0));
        assert!(points.contains(&(times[77_777], 9.0)) && points.contains(&(times[12_345], -9.0)));
        assert!(points.iter().all(|p| p.1.is_finite()));
        // Short series are drawn as they are.
        assert_eq!(decimate(&times[..10], &values[..10], 500).len(), 9);
    }

    #[test]
    fn each_arm_has_its_own_marks() {
        let arms = ["left", "right"];
        assert_eq!(arm_of("left_ee_x", &arms), Some("left"));
        assert_eq!(arm_of("right_gripper", &arms), Some("right"));
        assert_eq!(arm_of("leftover", &arms), None);
        assert_eq!(arm_of("ee_x", &["main"]), None);
    }

    #[test]
    fn engaged_spans_close_at_release_or_at_the_end() {
        let e = |frame: u64, arm: &str, kind| EpisodeEvent {
            frame_index: frame,
            timestamp: frame as f64 / 10.0,
            arm: arm.into(),
            kind,
            count: 1,
            detail: String::new(),
        };
        let events = [
            e(2, "a", EventKind::ClutchEngage),
            e(3, "b", EventKind::ClutchEngage),
            e(5, "a", EventKind::GateRejected),
            e(6, "a", EventKind::ClutchRelease),
        ];
        let spans = engaged_spans(&events, 2.0);
        assert_eq!(spans, [("a".to_owned(), 0.2, 0.6), ("b".to_owned(), 0.3, 2.0)]);
    }
}
