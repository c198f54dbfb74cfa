//! Button-event constructors: the one set the SDK, the gateway and tests build phone buttons with.

use crate::v1;

/// Clutch toggle (the Android app's volume key).
pub fn clutch_toggle() -> v1::ButtonEvent {
    clutch(v1::clutch_command::Kind::Toggle)
}

/// Hold-to-move pressed.
pub fn clutch_engage() -> v1::ButtonEvent {
    clutch(v1::clutch_command::Kind::Engage)
}

/// Hold-to-move released.
pub fn clutch_disengage() -> v1::ButtonEvent {
    clutch(v1::clutch_command::Kind::Disengage)
}

/// A clutch command of `kind`.
pub fn clutch(kind: v1::clutch_command::Kind) -> v1::ButtonEvent {
    v1::ButtonEvent {
        event: Some(v1::button_event::Event::Clutch(v1::ClutchCommand {
            kind: kind as i32,
        })),
    }
}

/// Gripper toggle.
pub fn gripper_toggle() -> v1::ButtonEvent {
    v1::ButtonEvent {
        event: Some(v1::button_event::Event::Gripper(v1::GripperCommand {
            kind: v1::gripper_command::Kind::Toggle as i32,
            position: 0.0,
        })),
    }
}

/// Absolute gripper position, 0 = open, 1 = closed.
pub fn gripper_set(position: f64) -> v1::ButtonEvent {
    v1::ButtonEvent {
        event: Some(v1::button_event::Event::Gripper(v1::GripperCommand {
            kind: v1::gripper_command::Kind::Set as i32,
            position,
        })),
    }
}

/// Hand the arm back to the policy waiting for it (nothing moves until its next fresh chunk).
pub fn hand_back() -> v1::ButtonEvent {
    v1::ButtonEvent {
        event: Some(v1::button_event::Event::HandBack(v1::HandBackCommand {})),
    }
}

/// Start recording with `task`.
pub fn record_start(task: &str) -> v1::ButtonEvent {
    record(v1::record_command::Kind::Start, task)
}

/// Stop and save.
pub fn record_stop() -> v1::ButtonEvent {
    record(v1::record_command::Kind::Stop, "")
}

/// Stop and save with the operator's outcome.
pub fn record_stop_with(outcome: v1::EpisodeOutcome) -> v1::ButtonEvent {
    v1::ButtonEvent {
        event: Some(v1::button_event::Event::Record(v1::RecordCommand {
            kind: v1::record_command::Kind::Stop as i32,
            outcome: outcome as i32,
            ..v1::RecordCommand::default()
        })),
    }
}

/// Stop and discard.
pub fn record_discard() -> v1::ButtonEvent {
    record(v1::record_command::Kind::Discard, "")
}

/// Save the last seconds the recorder kept while idle as an episode of `task`, with the operator's outcome.
pub fn save_highlight(task: &str, outcome: v1::EpisodeOutcome) -> v1::ButtonEvent {
    v1::ButtonEvent {
        event: Some(v1::button_event::Event::Record(v1::RecordCommand {
            kind: v1::record_command::Kind::SaveHighlight as i32,
            task: task.to_owned(),
            outcome: outcome as i32,
        })),
    }
}

/// A record command of `kind` (`task` matters for a start only).
pub fn record(kind: v1::record_command::Kind, task: &str) -> v1::ButtonEvent {
    v1::ButtonEvent {
        event: Some(v1::button_event::Event::Record(v1::RecordCommand {
            kind: kind as i32,
            task: task.to_owned(),
            ..v1::RecordCommand::default()
        })),
    }
}
