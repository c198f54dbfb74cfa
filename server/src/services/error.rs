//! The only place domain errors become statuses. Below the service layer nothing knows about `tonic::Status`:
//! each layer returns its own error enum, and each maps here to the status code a client can act on, with the
//! error's message. A code is chosen once per error, so every service returns the same status for the same
//! failure.

use crate::app::LookupError;
use crate::arm::ArmError;
use crate::policy_session::PolicyError;
use crate::recording::RecordingError;
use phone2act_bridges::BridgeError;
use phone2act_core::ArbiterError;
use phone2act_proto::ConvertError;
use phone2act_recorder::error::RecorderError;
use tonic::Status;

impl From<ArmError> for Status {
    fn from(e: ArmError) -> Self {
        let message = e.to_string();
        match e {
            ArmError::Refused { source, .. } => match source {
                ArbiterError::PhoneBound => Status::already_exists(message),
                // The session lost its arm to another phone: it cannot continue.
                ArbiterError::PhoneReplaced => Status::aborted(message),
                ArbiterError::DrivenByPhone
                | ArbiterError::NotReady(_)
                | ArbiterError::NotOwner { .. }
                | ArbiterError::NotControlling
                | ArbiterError::DrivenWhileHoming { .. } => Status::failed_precondition(message),
                ArbiterError::Chunk(_) => Status::invalid_argument(message),
            },
            ArmError::InvalidStep { .. } => Status::invalid_argument(message),
            // A feature the bridge lacks (a scene on a real arm) is UNIMPLEMENTED, anything else INTERNAL.
            ArmError::Bridge {
                source: BridgeError::Unsupported(_),
                ..
            } => Status::unimplemented(message),
            ArmError::Bridge { .. } => Status::internal(message),
            // Configuration mistakes are found at start; a request never causes them.
            ArmError::Config { .. }
            | ArmError::JointModeUnsupported { .. }
            | ArmError::LerobotLayoutUnsupported { .. } => Status::failed_precondition(message),
        }
    }
}

impl From<LookupError> for Status {
    fn from(e: LookupError) -> Self {
        Status::not_found(e.to_string())
    }
}

/// A wire value with no meaning (both types are foreign here, so this is a function, not a `From`).
pub fn wire(e: &ConvertError) -> Status {
    Status::invalid_argument(e.to_string())
}

impl From<RecordingError> for Status {
    fn from(e: RecordingError) -> Self {
        let message = e.to_string();
        match e {
            RecordingError::Closed => Status::unavailable(message),
            RecordingError::Recorder(e) => recorder_status(&e, message),
            RecordingError::FractionalFps(_) => Status::failed_precondition(message),
            RecordingError::WatchThread(_) => Status::internal(message),
        }
    }
}

fn recorder_status(e: &RecorderError, message: String) -> Status {
    match e {
        RecorderError::AlreadyRecording(_)
        | RecorderError::NotRecording
        | RecorderError::NothingToRerecord
        | RecorderError::FpsMismatch { .. }
        | RecorderError::FormatMismatch { .. }
        | RecorderError::FeatureMismatch { .. }
        | RecorderError::InvalidSpec(_) => Status::failed_precondition(message),
        RecorderError::TaskTooLong { .. } | RecorderError::EmptyTask | RecorderError::EmptyEpisode(_) => {
            Status::invalid_argument(message)
        }
        RecorderError::DiskFull { .. } => Status::resource_exhausted(message),
        _ => Status::internal(message),
    }
}

impl From<PolicyError> for Status {
    fn from(e: PolicyError) -> Self {
        let message = e.to_string();
        match e {
            PolicyError::Lookup(e) => e.into(),
            PolicyError::NoFeedback(_) => Status::unavailable(message),
            PolicyError::Jpeg { .. } | PolicyError::NoRandomness(_) => Status::internal(message),
            PolicyError::ArmNotOpened(_) => Status::failed_precondition(message),
            PolicyError::EmptyChunk
            | PolicyError::StepWidth { .. }
            | PolicyError::NotFinite { .. }
            | PolicyError::StepPeriod(_)
            | PolicyError::UnknownObservation(_)
            | PolicyError::ObservationLacksArm { .. } => Status::invalid_argument(message),
            PolicyError::UnknownSession => Status::not_found(message),
            PolicyError::Arm(e) => e.into(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use phone2act_core::{ChunkError, NotReady, Owner};
    use tonic::Code;

    fn refused(source: ArbiterError) -> Status {
        ArmError::Refused {
            arm: "main".into(),
            source,
        }
        .into()
    }

    #[test]
    fn every_refusal_is_a_status_a_client_can_act_on() {
        assert_eq!(refused(ArbiterError::PhoneBound).code(), Code::AlreadyExists);
        assert_eq!(refused(ArbiterError::PhoneReplaced).code(), Code::Aborted);
        let not_ready = refused(NotReady::NoFeedback.into());
        assert_eq!(not_ready.code(), Code::FailedPrecondition);
        assert_eq!(
            not_ready.message(),
            "arm \"main\" is not ready: its bridge has sent no valid feedback yet (no measured pose)"
        );
        assert_eq!(
            refused(ArbiterError::NotControlling).code(),
            Code::FailedPrecondition
        );
        assert_eq!(refused(ChunkError::Empty.into()).code(), Code::InvalidArgument);
        let homing = refused(ArbiterError::DrivenWhileHoming {
            owner: Owner::Policy {
                name: "evaluator".into(),
            },
        });
        assert_eq!(
            (homing.code(), homing.message()),
            (
                Code::FailedPrecondition,
                "arm \"main\" is driven by policy \"evaluator\"; release it before homing the arm"
            )
        );
    }

    #[test]
    fn a_bridge_without_the_feature_is_unimplemented() {
        let bridge = |source| -> Status {
            ArmError::Bridge {
                arm: "main".into(),
                source,
            }
            .into()
        };
        let missing = bridge(BridgeError::Unsupported(
            "scene reset is not supported by the dobot bridge".into(),
        ));
        assert_eq!(
            (missing.code(), missing.message()),
            (
                Code::Unimplemented,
                "arm \"main\": scene reset is not supported by the dobot bridge"
            )
        );
        assert_eq!(bridge(BridgeError::Protocol("x".into())).code(), Code::Internal);
    }

    #[test]
    fn each_error_keeps_its_code_and_message() {
        let cases: [(Status, Code, &str); 6] = [
            (
                LookupError::UnknownArm {
                    arm: "x".into(),
                    configured: "left, right".into(),
                }
                .into(),
                Code::NotFound,
                "unknown arm \"x\"; configured arms: left, right",
            ),
            (
                RecordingError::Closed.into(),
                Code::Unavailable,
                "the recorder is closed (server shutting down)",
            ),
            (
                RecordingError::from(RecorderError::NotRecording).into(),
                Code::FailedPrecondition,
                &RecorderError::NotRecording.to_string(),
            ),
            (
                RecordingError::from(RecorderError::EmptyTask).into(),
                Code::InvalidArgument,
                &RecorderError::EmptyTask.to_string(),
            ),
            (
                PolicyError::NoFeedback("left".into()).into(),
                Code::Unavailable,
                "arm \"left\" has no robot feedback yet",
            ),
            (
                PolicyError::UnknownSession.into(),
                Code::NotFound,
                "no open policy session with this session_id (use SessionReady.session_id)",
            ),
        ];
        for (status, code, message) in cases {
            assert_eq!((status.code(), status.message()), (code, message));
        }
    }
}
