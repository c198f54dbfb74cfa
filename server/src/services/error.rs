//! The only place domain errors become statuses. Below the service layer nothing knows about `tonic::Status`:
//! each layer returns its own error enum, and each maps here to the status code a client can act on, with the
//! error's message. A code is chosen once per error, so every service returns the same status for the same
//! failure.

use crate::app::LookupError;
use crate::arm::ArmError;
use crate::policy_session::PolicyError;
use crate::recording::RecordingError;
use phone2act_bridges::BridgeError;
use phone2act_bridges::remote::RemoteError;
use phone2act_core::ArbiterError;
use phone2act_dataset::error::RecorderError;
use phone2act_proto::ConvertError;
use std::time::Duration;
use tonic::Status;

/// A request that breaks the API's contract before any domain code runs: what the services' own checks find
/// (the first message of a stream, sizes, ranges, a missing field). Built in the services, mapped here like
/// every other error.
#[derive(Debug, thiserror::Error)]
pub enum RequestError {
    /// A stream's first message is not the hello it must start with, or the stream ended before it.
    #[error("{0}")]
    NoHello(&'static str),
    /// A stream sent its hello again.
    #[error("{0} sent twice")]
    HelloTwice(&'static str),
    #[error("no first sample within {timeout_s} s: a phone session starts by naming its arm")]
    NoFirstSample { timeout_s: u64 },
    #[error("{field} is {len} bytes, the limit is {limit}")]
    TooLong {
        field: &'static str,
        len: usize,
        limit: usize,
    },
    /// A number outside its documented range; `range` says the range in the API's words.
    #[error("{field} must be {range}, got {value}")]
    OutOfRange {
        field: &'static str,
        range: String,
        value: f64,
    },
    #[error("missing {0}")]
    Missing(&'static str),
    /// A request-specific refusal whose message says what was wrong (a pushed frame, a bridge's message).
    #[error("{0}")]
    Refused(String),
    /// The server could not do its part (a queue or thread it needs); not the client's fault.
    #[error("{0}")]
    Internal(String),
}

impl From<RequestError> for Status {
    fn from(e: RequestError) -> Self {
        let message = e.to_string();
        match e {
            RequestError::NoFirstSample { .. } => Status::deadline_exceeded(message),
            RequestError::Internal(_) => Status::internal(message),
            RequestError::NoHello(_)
            | RequestError::HelloTwice(_)
            | RequestError::TooLong { .. }
            | RequestError::OutOfRange { .. }
            | RequestError::Missing(_)
            | RequestError::Refused(_) => Status::invalid_argument(message),
        }
    }
}

/// A `WatchStatus`/`Watch` interval: 0 means `default_s`; anything else must be a finite, non-negative number
/// of seconds, and is kept within 0.01 s..1 h.
pub fn watch_interval(interval_s: f64, default_s: f64) -> Result<Duration, RequestError> {
    if !interval_s.is_finite() || interval_s < 0.0 {
        return Err(RequestError::OutOfRange {
            field: "interval_s",
            range: ">= 0".to_owned(),
            value: interval_s,
        });
    }
    let interval_s = if interval_s == 0.0 {
        default_s
    } else {
        interval_s.clamp(0.01, 3600.0)
    };
    Ok(Duration::from_secs_f64(interval_s))
}

/// Refuses a string longer than `limit` bytes.
pub fn check_len(field: &'static str, value: &str, limit: usize) -> Result<(), RequestError> {
    if value.len() > limit {
        return Err(RequestError::TooLong {
            field,
            len: value.len(),
            limit,
        });
    }
    Ok(())
}

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
                | ArbiterError::DrivenWhileHoming { .. }
                // States of the arm, not bad chunks: a waiting policy waits for the hand-back, a handed-back one
                // must observe again.
                | ArbiterError::PolicyWaiting { .. }
                | ArbiterError::BeforeHandBack { .. } => Status::failed_precondition(message),
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
            | ArmError::LerobotLayoutUnsupported { .. }
            | ArmError::FlightLog { .. }
            | ArmError::JointStageUnsupported { .. }
            | ArmError::JointModelMismatch { .. } => Status::failed_precondition(message),
        }
    }
}

/// A remote bridge's attachment refused or ended (both types are foreign here: a function, not a `From`).
pub fn remote(e: &RemoteError) -> Status {
    let message = e.to_string();
    match e {
        RemoteError::NoJoints
        | RemoteError::JointNamesMismatch { .. }
        | RemoteError::InvalidFeedback(_)
        | RemoteError::UndeclaredScene => Status::invalid_argument(message),
        // The attachment ended under the bridge (replaced, detached, shut down): it may attach again.
        RemoteError::Superseded | RemoteError::Detached | RemoteError::ShutDown => Status::aborted(message),
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
            RecordingError::FractionalFps(_) | RecordingError::Config(_) => {
                Status::failed_precondition(message)
            }
            RecordingError::WatchThread(_) => Status::internal(message),
        }
    }
}

fn recorder_status(e: &RecorderError, message: String) -> Status {
    match e {
        RecorderError::AlreadyRecording(_)
        | RecorderError::NotRecording
        | RecorderError::NothingToRerecord
        | RecorderError::HighlightOff
        | RecorderError::HighlightWhileRecording(_)
        | RecorderError::NothingBuffered
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
            | PolicyError::KeepSteps { .. }
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

    #[test]
    fn a_request_that_breaks_the_contract_is_invalid_unless_the_server_failed() {
        let cases: Vec<(Status, Code, &str)> = vec![
            (
                RequestError::NoHello("the stream ended before BridgeHello").into(),
                Code::InvalidArgument,
                "the stream ended before BridgeHello",
            ),
            (
                RequestError::HelloTwice("PolicyHello").into(),
                Code::InvalidArgument,
                "PolicyHello sent twice",
            ),
            (
                RequestError::NoFirstSample { timeout_s: 5 }.into(),
                Code::DeadlineExceeded,
                "no first sample within 5 s: a phone session starts by naming its arm",
            ),
            (
                check_len("client_name", &"x".repeat(65), 64).unwrap_err().into(),
                Code::InvalidArgument,
                "client_name is 65 bytes, the limit is 64",
            ),
            (
                RequestError::Missing("chunk").into(),
                Code::InvalidArgument,
                "missing chunk",
            ),
            (
                RequestError::Internal("event queue".into()).into(),
                Code::Internal,
                "event queue",
            ),
            (
                remote(&RemoteError::Superseded),
                Code::Aborted,
                "another bridge attached to this arm and replaced this one",
            ),
            (
                remote(&RemoteError::NoJoints),
                Code::InvalidArgument,
                "a bridge must name at least one joint",
            ),
        ];
        for (status, code, message) in cases {
            assert_eq!((status.code(), status.message()), (code, message));
        }
        assert!(
            check_len("client_name", &"x".repeat(64), 64).is_ok(),
            "the limit itself is allowed"
        );
    }

    #[test]
    fn a_watch_interval_is_a_finite_non_negative_number_of_seconds() {
        assert_eq!(
            watch_interval(0.0, 0.5).unwrap(),
            Duration::from_millis(500),
            "0 is the default"
        );
        assert_eq!(watch_interval(0.2, 0.5).unwrap(), Duration::from_millis(200));
        assert_eq!(
            watch_interval(1e-6, 0.5).unwrap(),
            Duration::from_millis(10),
            "at most 100 per second"
        );
        assert_eq!(watch_interval(1e9, 0.5).unwrap(), Duration::from_hours(1));
        for bad in [-0.1, f64::NAN, f64::INFINITY] {
            let status = Status::from(watch_interval(bad, 0.5).unwrap_err());
            assert_eq!(status.code(), Code::InvalidArgument);
            assert_eq!(status.message(), format!("interval_s must be >= 0, got {bad}"));
        }
    }
}
