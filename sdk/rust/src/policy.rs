//! The Policy service: a session that receives observations and pushes action chunks.

use crate::{AuthChannel, Client, Error, Result};
use phone2act_proto::v1;
use phone2act_proto::v1::policy_client::PolicyClient;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;

impl Client {
    /// Opens a policy session with `hello`; returns once the server answered with `SessionReady`.
    pub async fn policy(&self, hello: v1::PolicyHello) -> Result<PolicySession> {
        PolicySession::open(self.policy_raw(), hello).await
    }

    /// The raw generated Policy client.
    pub fn policy_raw(&self) -> PolicyClient<AuthChannel> {
        PolicyClient::with_interceptor(self.transport(), self.auth())
    }
}

/// An open policy session.
#[derive(Debug)]
pub struct PolicySession {
    tx: mpsc::Sender<v1::PolicyRequest>,
    events: tonic::Streaming<v1::PolicyEvent>,
    ready: v1::SessionReady,
}

impl PolicySession {
    async fn open(mut client: PolicyClient<AuthChannel>, hello: v1::PolicyHello) -> Result<Self> {
        // A few slots: chunks are small and rare (a few per second); the bound keeps a stuck server from
        // growing the queue.
        let (tx, rx) = mpsc::channel(8);
        tx.send(v1::PolicyRequest {
            request: Some(v1::policy_request::Request::Hello(hello)),
        })
        .await
        .map_err(|_| Error::Closed)?;
        let mut events = client.session(ReceiverStream::new(rx)).await?.into_inner();
        let ready = match events.message().await? {
            Some(v1::PolicyEvent {
                event: Some(v1::policy_event::Event::Ready(ready)),
            }) => ready,
            Some(other) => return Err(Error::Protocol(format!("expected SessionReady, got {other:?}"))),
            None => return Err(Error::Closed),
        };
        Ok(Self { tx, events, ready })
    }

    /// What the server said when the session opened: the session id and each arm's layout.
    pub fn ready(&self) -> &v1::SessionReady {
        &self.ready
    }

    /// The next event (observation, control change, chunk verdict); `Ok(None)` when the stream ended.
    pub async fn next_event(&mut self) -> Result<Option<v1::policy_event::Event>> {
        loop {
            match self.events.message().await? {
                Some(v1::PolicyEvent { event: Some(event) }) => return Ok(Some(event)),
                Some(v1::PolicyEvent { event: None }) => {}
                None => return Ok(None),
            }
        }
    }

    /// The next observation, skipping other events.
    pub async fn next_observation(&mut self) -> Result<v1::Observation> {
        loop {
            match self.next_event().await? {
                Some(v1::policy_event::Event::Observation(obs)) => return Ok(obs),
                Some(_) => {}
                None => return Err(Error::Closed),
            }
        }
    }

    /// Pushes an action chunk.
    pub async fn push_chunk(&self, chunk: v1::ActionChunk) -> Result<()> {
        self.request(v1::policy_request::Request::Chunk(chunk)).await
    }

    /// Asks for one observation now.
    pub async fn request_observation(&self) -> Result<()> {
        self.request(v1::policy_request::Request::Observe(v1::ObservationRequest {}))
            .await
    }

    /// Says the policy is loading: its arms hold until its first chunk, at most the arm's
    /// `chunk.max_loading_s` from the first call (later calls are keep-alives that do not extend it). The server
    /// answers with a `LoadingAccepted` event.
    pub async fn loading(&self) -> Result<()> {
        self.request(v1::policy_request::Request::Loading(v1::PolicyLoading {}))
            .await
    }

    /// Gives up control; the arms hold.
    pub async fn release(&self) -> Result<()> {
        self.request(v1::policy_request::Request::Release(v1::ReleaseControl {}))
            .await
    }

    async fn request(&self, request: v1::policy_request::Request) -> Result<()> {
        self.tx
            .send(v1::PolicyRequest {
                request: Some(request),
            })
            .await
            .map_err(|_| Error::Closed)
    }
}

impl PolicySession {
    /// Pushes a chunk as a unary call: a bad chunk comes back as an error status instead of an event.
    pub async fn push_chunk_checked(
        &self,
        client: &Client,
        chunk: v1::ActionChunk,
    ) -> Result<v1::ChunkAccepted> {
        let request = v1::PushChunkRequest {
            session_id: self.ready.session_id.clone(),
            chunk: Some(chunk),
        };
        Ok(client.policy_raw().push_chunk(request).await?.into_inner())
    }
}
