//! Policy wire enums ⇄ core types.

use crate::ConvertError;
use crate::v1;
use phone2act_core::ActionMode;

impl From<v1::ActionMode> for ActionMode {
    /// Unspecified means the documented default, relative to the observation.
    fn from(mode: v1::ActionMode) -> Self {
        match mode {
            v1::ActionMode::Unspecified | v1::ActionMode::DeltaEe => Self::Relative,
            v1::ActionMode::AbsoluteEe => Self::Absolute,
            v1::ActionMode::Joint => Self::Joint,
        }
    }
}

impl From<ActionMode> for v1::ActionMode {
    fn from(mode: ActionMode) -> Self {
        match mode {
            ActionMode::Relative => Self::DeltaEe,
            ActionMode::Absolute => Self::AbsoluteEe,
            ActionMode::Joint => Self::Joint,
        }
    }
}

/// A chunk's `mode` field as a core action mode.
pub fn action_mode(wire: i32) -> Result<ActionMode, ConvertError> {
    v1::ActionMode::try_from(wire)
        .map(ActionMode::from)
        .map_err(|_| ConvertError::UnknownEnum {
            what: "action mode",
            value: wire,
        })
}

/// The image encoding an observation request asks for: unset (or a value this server does not know) means
/// the documented default, JPEG.
pub fn requested_encoding(wire: i32) -> v1::ImageEncoding {
    match v1::ImageEncoding::try_from(wire) {
        Ok(v1::ImageEncoding::Unspecified) | Err(_) => v1::ImageEncoding::Jpeg,
        Ok(encoding) => encoding,
    }
}

impl From<v1::policy_event::Event> for v1::PolicyEvent {
    fn from(event: v1::policy_event::Event) -> Self {
        Self { event: Some(event) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_core_mode_survives_the_wire_and_unknown_values_are_named() {
        for mode in [ActionMode::Relative, ActionMode::Absolute, ActionMode::Joint] {
            assert_eq!(action_mode(v1::ActionMode::from(mode) as i32), Ok(mode));
        }
        assert_eq!(action_mode(0), Ok(ActionMode::Relative));
        assert_eq!(action_mode(99).unwrap_err().to_string(), "unknown action mode 99");
    }

    #[test]
    fn an_unset_or_unknown_encoding_asks_for_jpeg() {
        assert_eq!(requested_encoding(0), v1::ImageEncoding::Jpeg);
        assert_eq!(requested_encoding(77), v1::ImageEncoding::Jpeg);
        assert_eq!(
            requested_encoding(v1::ImageEncoding::None as i32),
            v1::ImageEncoding::None
        );
        assert_eq!(
            requested_encoding(v1::ImageEncoding::Rgb8 as i32),
            v1::ImageEncoding::Rgb8
        );
    }
}
