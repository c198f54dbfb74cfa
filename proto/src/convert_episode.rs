//! Episode and recording wire messages ⇄ plain values.

use crate::ConvertError;
use crate::v1;

pub use phone2act_core::config::MAX_TASK_BYTES;

/// What a record button asks the recorder to do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RecordAction<'a> {
    /// Start an episode with this task text.
    Start { task: &'a str },
    /// Stop and save the episode in progress, with the operator's outcome (`Some(true)`: a success).
    Stop { success: Option<bool> },
    /// Stop and throw away the episode in progress.
    Discard,
    /// Save the last seconds the recorder kept while idle as an episode of this task, with the operator's
    /// outcome.
    SaveHighlight { task: &'a str, success: Option<bool> },
}

impl<'a> TryFrom<&'a v1::RecordCommand> for RecordAction<'a> {
    type Error = ConvertError;

    fn try_from(command: &'a v1::RecordCommand) -> Result<Self, ConvertError> {
        match v1::record_command::Kind::try_from(command.kind) {
            Ok(v1::record_command::Kind::Start) => Ok(Self::Start { task: &command.task }),
            Ok(v1::record_command::Kind::Stop) => Ok(Self::Stop {
                success: outcome_success(command.outcome)?,
            }),
            Ok(v1::record_command::Kind::Discard) => Ok(Self::Discard),
            Ok(v1::record_command::Kind::SaveHighlight) => Ok(Self::SaveHighlight {
                task: &command.task,
                success: outcome_success(command.outcome)?,
            }),
            Ok(v1::record_command::Kind::Unspecified) | Err(_) => Err(ConvertError::UnknownEnum {
                what: "record command",
                value: command.kind,
            }),
        }
    }
}

/// A wire episode outcome as the recorder takes it: `Some(true)` for a success, `Some(false)` for a failure,
/// `None` when not given; an unknown value is refused (nothing is stopped with an outcome it cannot keep).
pub fn outcome_success(outcome: i32) -> Result<Option<bool>, ConvertError> {
    match v1::EpisodeOutcome::try_from(outcome) {
        Ok(v1::EpisodeOutcome::Unspecified) => Ok(None),
        Ok(v1::EpisodeOutcome::Success) => Ok(Some(true)),
        Ok(v1::EpisodeOutcome::Failure) => Ok(Some(false)),
        Err(_) => Err(ConvertError::UnknownEnum {
            what: "episode outcome",
            value: outcome,
        }),
    }
}

/// The short lower-case name of a wire recording phase (`"unknown"` for unset or unknown values), as status
/// displays and JSON show it.
pub fn phase_name(phase: i32) -> &'static str {
    match v1::RecordingPhase::try_from(phase) {
        Ok(v1::RecordingPhase::Idle) => "idle",
        Ok(v1::RecordingPhase::Recording) => "recording",
        Ok(v1::RecordingPhase::Paused) => "paused",
        Ok(v1::RecordingPhase::Saving) => "saving",
        Ok(v1::RecordingPhase::Unspecified) | Err(_) => "unknown",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::buttons;

    #[test]
    fn record_buttons_become_actions_and_unknown_kinds_are_refused() {
        let action = |b: v1::ButtonEvent| match b.event {
            Some(v1::button_event::Event::Record(r)) => RecordAction::try_from(&r).map(|a| format!("{a:?}")),
            _ => unreachable!("a record builder builds a record command"),
        };
        assert_eq!(
            action(buttons::record_start("pick")).unwrap(),
            r#"Start { task: "pick" }"#
        );
        assert_eq!(action(buttons::record_stop()).unwrap(), "Stop { success: None }");
        assert_eq!(
            action(buttons::record_stop_with(v1::EpisodeOutcome::Success)).unwrap(),
            "Stop { success: Some(true) }"
        );
        assert_eq!(
            action(buttons::record_stop_with(v1::EpisodeOutcome::Failure)).unwrap(),
            "Stop { success: Some(false) }"
        );
        let unknown = v1::RecordCommand {
            kind: v1::record_command::Kind::Stop as i32,
            outcome: 9,
            ..v1::RecordCommand::default()
        };
        assert_eq!(
            RecordAction::try_from(&unknown).unwrap_err().to_string(),
            "unknown episode outcome 9"
        );
        assert_eq!(action(buttons::record_discard()).unwrap(), "Discard");
        assert_eq!(
            action(buttons::save_highlight("pick", v1::EpisodeOutcome::Unspecified)).unwrap(),
            r#"SaveHighlight { task: "pick", success: None }"#
        );
        assert_eq!(
            action(buttons::save_highlight("pick", v1::EpisodeOutcome::Failure)).unwrap(),
            r#"SaveHighlight { task: "pick", success: Some(false) }"#
        );
        let bad = v1::RecordCommand {
            kind: 42,
            ..v1::RecordCommand::default()
        };
        assert_eq!(
            RecordAction::try_from(&bad).unwrap_err().to_string(),
            "unknown record command 42"
        );
    }

    #[test]
    fn phases_have_short_names() {
        assert_eq!(phase_name(v1::RecordingPhase::Recording as i32), "recording");
        assert_eq!(phase_name(v1::RecordingPhase::Idle as i32), "idle");
        assert_eq!(phase_name(0), "unknown");
        assert_eq!(phase_name(99), "unknown");
    }
}
