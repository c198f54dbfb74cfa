//! Inputs the core's unit tests build alike.

use crate::arbiter::Input;
use crate::chunk::{ActionChunk, ChunkStep};
use nalgebra::Isometry3;

/// A chunk from policy `session`: `targets` with the gripper half closed, 0.1 s apart from `anchor_s`,
/// answering an observation taken then.
pub(crate) fn chunk_input(session: u64, anchor_s: f64, targets: &[Isometry3<f64>]) -> Input {
    Input::Chunk {
        session,
        chunk: ActionChunk {
            steps: targets
                .iter()
                .map(|&robot_from_target| ChunkStep {
                    robot_from_target,
                    gripper: 0.5,
                })
                .collect(),
            anchor_time_s: anchor_s,
            step_period_s: 0.1,
        },
        observed_s: anchor_s,
    }
}
