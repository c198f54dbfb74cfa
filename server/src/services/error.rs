//! The one place where domain errors become gRPC statuses. Below the service layer nothing knows about
//! `tonic::Status`: the domain returns its own error enums, and each maps here to the status code a client
//! can act on, with the error's message.

use crate::arm::ArmError;
use phone2act_core::ArbiterError;
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
                | ArbiterError::NotControlling => Status::failed_precondition(message),
                ArbiterError::Chunk(_) => Status::invalid_argument(message),
            },
            ArmError::InvalidStep { .. } => Status::invalid_argument(message),
            // Configuration mistakes are found at start; a request never causes them.
            ArmError::Config { .. }
            | ArmError::JointModeUnsupported { .. }
            | ArmError::LerobotLayoutUnsupported { .. } => Status::failed_precondition(message),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use phone2act_core::{ChunkError, NotReady};
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
    }
}
