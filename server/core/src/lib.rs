//! Pure phone2act domain logic: poses, the teleop planner, the safety gate, chunk-executor math, kinematics
//! and the action/state vector layouts. No I/O, no tokio, no clock reads: every time is an argument, so
//! everything here is deterministic and property-testable.

pub mod kinematics;
