//! The Scene service: a simulated arm's ball-and-basket scene.

use crate::{Client, Result};
use phone2act_proto::v1;
use phone2act_proto::v1::scene_client::SceneClient;

impl Client {
    /// The Scene service: reset and read a simulated arm's ball-and-basket scene.
    pub fn scene(&self) -> SceneApi {
        SceneApi {
            inner: SceneClient::with_interceptor(self.transport(), self.auth()),
        }
    }
}

/// Typed access to the Scene service.
#[derive(Clone, Debug)]
pub struct SceneApi {
    inner: SceneClient<crate::AuthChannel>,
}

impl SceneApi {
    /// Re-draws `arm`'s scene from `seed` (`None`: the arm's next seed); `home_arm` also puts the simulated
    /// arm at its initial joints, which the server refuses while a source drives it.
    pub async fn reset(&mut self, arm: &str, seed: Option<u64>, home_arm: bool) -> Result<v1::SceneState> {
        Ok(self
            .inner
            .reset(v1::ResetSceneRequest {
                arm: arm.to_owned(),
                seed,
                home_arm,
            })
            .await?
            .into_inner())
    }

    /// `arm`'s scene now.
    pub async fn get(&mut self, arm: &str) -> Result<v1::SceneState> {
        Ok(self
            .inner
            .get(v1::GetSceneRequest { arm: arm.to_owned() })
            .await?
            .into_inner())
    }
}
