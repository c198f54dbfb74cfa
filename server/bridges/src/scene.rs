//! The task scene around an arm, as the API reports it: a ball and a basket on a table. Only the simulator
//! has one; the [`crate::Bridge`] trait speaks of it in these types, which belong to no bridge.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// Where the ball is and what it is doing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum BallState {
    /// On the table or in the basket.
    Resting,
    /// In the gripper; the offset is the ball centre in the tool frame at the moment of the grasp.
    Held { tcp_from_ball: Vector3<f64> },
    /// In free fall.
    Falling { velocity_m_s: Vector3<f64> },
}

/// The task scene as the API reports it (see `phone2act.v1.SceneState`).
#[derive(Clone, Debug, PartialEq)]
pub struct SceneState {
    /// Seed the scene was drawn from; 0 with `resets == 0` is the configured start (`ball_xy_m`), not drawn.
    pub seed: u64,
    /// Resets since the world was made.
    pub resets: u64,
    pub ball_center_m: Vector3<f64>,
    pub ball_state: BallState,
    pub ball_radius_m: f64,
    pub basket_xy_m: [f64; 2],
    pub basket_radius_m: f64,
    pub basket_height_m: f64,
    /// The ball rests in the basket.
    pub task_success: bool,
    pub ball_area_m: TableArea,
    pub basket_area_m: Option<TableArea>,
}

/// An axis-aligned rectangle on the table, robot base frame.
#[derive(Clone, Copy, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TableArea {
    pub x_min_m: f64,
    pub x_max_m: f64,
    pub y_min_m: f64,
    pub y_max_m: f64,
}

impl TableArea {
    /// The point at fractions `(u, v)` (each in 0..1) of the way from the minimum to the maximum corner.
    pub fn point_at(&self, u: f64, v: f64) -> [f64; 2] {
        [
            self.x_min_m + u * (self.x_max_m - self.x_min_m),
            self.y_min_m + v * (self.y_max_m - self.y_min_m),
        ]
    }

    /// The four corners.
    pub fn corners(&self) -> [[f64; 2]; 4] {
        [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)].map(|(u, v)| self.point_at(u, v))
    }

    /// Distance from (x, y) to the nearest point of the area (0 inside).
    pub fn distance_to(&self, [x, y]: [f64; 2]) -> f64 {
        let dx = (self.x_min_m - x).max(x - self.x_max_m).max(0.0);
        let dy = (self.y_min_m - y).max(y - self.y_max_m).max(0.0);
        dx.hypot(dy)
    }
}
