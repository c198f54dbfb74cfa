//! Gripper target: 0 = fully open, 1 = fully closed, driven by toggle or absolute commands.

use crate::config::GripperConfig;

/// A gripper command from the phone or a script.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum GripperCommand {
    /// Open if more than half closed, else close (the Android app's volume key, a phone button).
    Toggle,
    /// An absolute target in [0, 1]; values outside are clamped.
    Set(f64),
}

#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum GripperError {
    #[error("gripper target is not finite: {0}")]
    NonFinite(f64),
}

/// The gripper target of one arm.
#[derive(Debug, Clone, PartialEq)]
pub struct Gripper {
    binary: bool,
    target: f64,
}

impl Gripper {
    /// Starts at `initial` (clamped, snapped when binary; a non-finite value counts as open).
    pub fn new(config: &GripperConfig, initial: f64) -> Self {
        let mut g = Self {
            binary: config.binary,
            target: 0.0,
        };
        if initial.is_finite() {
            g.target = g.shape(initial);
        }
        g
    }

    pub fn target(&self) -> f64 {
        self.target
    }

    /// Takes the gripper's actual target as its own (what another source last sent), unshaped so that
    /// adopting it never moves the gripper; a non-finite value changes nothing.
    pub fn adopt(&mut self, target: f64) {
        if target.is_finite() {
            self.target = target.clamp(0.0, 1.0);
        }
    }

    /// Applies a command and returns the new target. An invalid command changes nothing.
    pub fn apply(&mut self, command: GripperCommand) -> Result<f64, GripperError> {
        let value = match command {
            GripperCommand::Toggle => {
                if self.target >= 0.5 {
                    0.0
                } else {
                    1.0
                }
            }
            GripperCommand::Set(v) if !v.is_finite() => return Err(GripperError::NonFinite(v)),
            GripperCommand::Set(v) => v,
        };
        self.target = self.shape(value);
        Ok(self.target)
    }

    fn shape(&self, value: f64) -> f64 {
        let v = value.clamp(0.0, 1.0);
        if self.binary {
            if v >= 0.5 { 1.0 } else { 0.0 }
        } else {
            v
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn toggle_and_set_in_both_modes() {
        let mut cont = Gripper::new(&GripperConfig { binary: false }, 0.3);
        assert!((cont.target() - 0.3).abs() < 1e-15);
        assert_eq!(cont.apply(GripperCommand::Toggle), Ok(1.0));
        assert_eq!(cont.apply(GripperCommand::Toggle), Ok(0.0));
        assert_eq!(cont.apply(GripperCommand::Set(0.7)), Ok(0.7));
        assert_eq!(cont.apply(GripperCommand::Set(3.0)), Ok(1.0));
        assert!(
            matches!(cont.apply(GripperCommand::Set(f64::NAN)), Err(GripperError::NonFinite(v)) if v.is_nan())
        );
        assert!(cont.apply(GripperCommand::Set(f64::INFINITY)).is_err());
        assert!(
            (cont.target() - 1.0).abs() < 1e-15,
            "a rejected command changes nothing"
        );

        let mut bin = Gripper::new(&GripperConfig { binary: true }, 0.3);
        assert!(bin.target().abs() < 1e-15);
        assert_eq!(bin.apply(GripperCommand::Set(0.7)), Ok(1.0));
        assert_eq!(bin.apply(GripperCommand::Toggle), Ok(0.0));
        assert_eq!(bin.apply(GripperCommand::Set(0.49)), Ok(0.0));
    }
}
