//! `phone2act.v1.Scene`: reset and read the task scene of a simulated arm (ball and basket), between
//! episodes and without a restart. Arms without a scene answer UNIMPLEMENTED.

use crate::app::App;
use crate::arm::ArmController;
use crate::services::error::RequestError;
use phone2act_bridges::sim::{BallState, SceneState, TableArea};
use phone2act_proto::v1;
use phone2act_proto::v1::scene_server::Scene;
use std::sync::Arc;
use tonic::{Request, Response, Status};

/// The Scene service adapter.
#[derive(Debug, Clone)]
pub struct SceneService {
    app: Arc<App>,
}

impl SceneService {
    /// A service over `app`.
    pub fn new(app: Arc<App>) -> Self {
        Self { app }
    }

    fn arm(&self, name: &str) -> Result<Arc<ArmController>, Status> {
        Ok(self.app.find_arm(name)?)
    }
}

#[tonic::async_trait]
impl Scene for SceneService {
    async fn reset(
        &self,
        request: Request<v1::ResetSceneRequest>,
    ) -> Result<Response<v1::SceneState>, Status> {
        let request = request.into_inner();
        let arm = self.arm(&request.arm)?;
        // A remote bridge's scene answers over its stream: the wait is a blocking one, off the async runtime
        // whose tasks carry that answer.
        let resetting = Arc::clone(&arm);
        let state =
            tokio::task::spawn_blocking(move || resetting.reset_scene(request.seed, request.home_arm))
                .await
                .map_err(|e| Status::from(RequestError::Internal(format!("scene reset task: {e}"))))??;
        tracing::info!(
            arm = %arm.name,
            seed = state.seed,
            home_arm = request.home_arm,
            ball_x_m = state.ball_center_m.x,
            ball_y_m = state.ball_center_m.y,
            "scene reset"
        );
        Ok(Response::new(scene_to_proto(&arm.name, &state)))
    }

    async fn get(&self, request: Request<v1::GetSceneRequest>) -> Result<Response<v1::SceneState>, Status> {
        let request = request.into_inner();
        let arm = self.arm(&request.arm)?;
        Ok(Response::new(scene_to_proto(&arm.name, &arm.scene()?)))
    }
}

fn area_to_proto(area: &TableArea) -> v1::TableArea {
    v1::TableArea {
        x_min_m: area.x_min_m,
        x_max_m: area.x_max_m,
        y_min_m: area.y_min_m,
        y_max_m: area.y_max_m,
    }
}

fn area_from_proto(area: &v1::TableArea) -> TableArea {
    TableArea {
        x_min_m: area.x_min_m,
        x_max_m: area.x_max_m,
        y_min_m: area.y_min_m,
        y_max_m: area.y_max_m,
    }
}

/// A scene as a remote bridge reports it (the inverse of [`scene_to_proto`]; a held or falling ball's
/// offset and velocity are not on the wire and read as zero). Refuses non-finite numbers.
pub fn scene_from_proto(scene: &v1::SceneState) -> Result<SceneState, String> {
    let vec = |v: &Option<v1::Vec3>, what: &str| {
        let v = v.as_ref().ok_or_else(|| format!("scene has no {what}"))?;
        let v = nalgebra::Vector3::new(v.x, v.y, v.z);
        if v.iter().all(|c| c.is_finite()) {
            Ok(v)
        } else {
            Err(format!("scene {what} is not finite"))
        }
    };
    let ball_center_m = vec(&scene.ball_position_m, "ball_position_m")?;
    let basket = vec(&scene.basket_position_m, "basket_position_m")?;
    let ball_state = match v1::BallState::try_from(scene.ball_state).unwrap_or_default() {
        v1::BallState::Held => BallState::Held {
            tcp_from_ball: nalgebra::Vector3::zeros(),
        },
        v1::BallState::Falling => BallState::Falling {
            velocity_m_s: nalgebra::Vector3::zeros(),
        },
        _ => BallState::Resting,
    };
    let scalars = [scene.ball_radius_m, scene.basket_radius_m, scene.basket_height_m];
    if !scalars.iter().all(|v| v.is_finite()) {
        return Err("scene radius or height is not finite".into());
    }
    Ok(SceneState {
        seed: scene.seed,
        resets: scene.resets,
        ball_center_m,
        ball_state,
        ball_radius_m: scene.ball_radius_m,
        basket_xy_m: [basket.x, basket.y],
        basket_radius_m: scene.basket_radius_m,
        basket_height_m: scene.basket_height_m,
        task_success: scene.success,
        ball_area_m: scene.ball_area_m.as_ref().map_or(
            TableArea {
                x_min_m: 0.0,
                x_max_m: 0.0,
                y_min_m: 0.0,
                y_max_m: 0.0,
            },
            area_from_proto,
        ),
        basket_area_m: scene.basket_area_m.as_ref().map(area_from_proto),
    })
}

/// The wire form of a scene.
pub fn scene_to_proto(arm: &str, state: &SceneState) -> v1::SceneState {
    let ball_state = match state.ball_state {
        BallState::Resting if state.task_success => v1::BallState::InBasket,
        BallState::Resting => v1::BallState::Resting,
        BallState::Held { .. } => v1::BallState::Held,
        BallState::Falling { .. } => v1::BallState::Falling,
    };
    let ball = state.ball_center_m;
    let [basket_x_m, basket_y_m] = state.basket_xy_m;
    v1::SceneState {
        arm: arm.to_owned(),
        seed: state.seed,
        ball_position_m: Some(v1::Vec3::new(ball.x, ball.y, ball.z)),
        ball_state: ball_state as i32,
        ball_radius_m: state.ball_radius_m,
        basket_position_m: Some(v1::Vec3::new(basket_x_m, basket_y_m, 0.0)),
        basket_radius_m: state.basket_radius_m,
        basket_height_m: state.basket_height_m,
        success: state.task_success,
        resets: state.resets,
        ball_area_m: Some(area_to_proto(&state.ball_area_m)),
        basket_area_m: state.basket_area_m.as_ref().map(area_to_proto),
    }
}
