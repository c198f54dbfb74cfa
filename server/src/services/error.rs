//! The only place domain errors become statuses: each layer's error enum maps to a `tonic::Status` here, so a
//! code is chosen once per error and every service returns the same status for the same failure.

use crate::app::LookupError;
use crate::policy_session::PolicyError;
use crate::recording::RecordingError;
use phone2act_proto::ConvertError;
use phone2act_recorder::error::RecorderError;
use tonic::Status;

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
            PolicyError::Arm(status) => status,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::Code;

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
