//! The System service: arms, cameras, status, dataset info.

use crate::{AuthChannel, Client, Result};
use phone2act_proto::v1;
use phone2act_proto::v1::system_client::SystemClient;

impl Client {
    /// The raw generated System client.
    pub fn system_raw(&self) -> SystemClient<AuthChannel> {
        SystemClient::with_interceptor(self.transport(), self.auth())
    }

    /// The System service: arms, cameras, status.
    pub fn system(&self) -> SystemApi {
        SystemApi {
            inner: self.system_raw(),
        }
    }
}

/// Typed access to the System service.
#[derive(Clone, Debug)]
pub struct SystemApi {
    inner: SystemClient<AuthChannel>,
}

impl SystemApi {
    /// Configured arms with their current state.
    pub async fn list_arms(&mut self) -> Result<Vec<v1::ArmState>> {
        Ok(self
            .inner
            .list_arms(v1::ListArmsRequest {})
            .await?
            .into_inner()
            .arms)
    }

    /// Configured cameras with their current health.
    pub async fn list_cameras(&mut self) -> Result<Vec<v1::CameraStatus>> {
        Ok(self
            .inner
            .list_cameras(v1::ListCamerasRequest {})
            .await?
            .into_inner()
            .cameras)
    }

    /// A status snapshot.
    pub async fn status(&mut self) -> Result<v1::SystemStatus> {
        Ok(self.inner.get_status(v1::GetStatusRequest {}).await?.into_inner())
    }

    /// The dataset the recorder writes to.
    pub async fn dataset_info(&mut self) -> Result<v1::DatasetInfo> {
        Ok(self
            .inner
            .get_dataset_info(v1::GetDatasetInfoRequest {})
            .await?
            .into_inner())
    }

    /// A stream of status snapshots every `interval_s`.
    pub async fn watch_status(&mut self, interval_s: f64) -> Result<tonic::Streaming<v1::SystemStatus>> {
        Ok(self
            .inner
            .watch_status(v1::WatchStatusRequest { interval_s })
            .await?
            .into_inner())
    }
}
